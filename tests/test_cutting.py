"""Cutting (tissue.cutting): the swept surface, the split along it with its quality bound, the
sides separated, the compliance exact through every cut step, mass, free fall of a cut-off piece,
cutting while in contact, and a cut mesh written to VTU."""

import numpy as np
import pytest
from test_cutting_compliance import DT, MATERIAL, TOLERANCE, compliances, direct_inverse, relative_error

from tissue.cutting.cutter import Cutter
from tissue.cutting.subdivision import MAX_CONDITION, MIN_DIHEDRAL, condition_numbers, split_element
from tissue.cutting.surface import CutPath, CutSurface, sweep
from tissue.fem.model import BodyModel
from tissue.mesh import box
from tissue.mesh.quality import min_dihedral_angles
from tissue.mesh.tetmesh import signed_volumes

SIZE = (0.1, 0.04, 0.04)


def pieces(model: BodyModel) -> np.ndarray:
    """Label of the connected piece (sharing nodes) of each element."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    tets = model.tets
    incidence = sp.csr_matrix((np.ones(tets.size), (np.repeat(np.arange(len(tets)), 4), tets.reshape(-1))),
                              shape=(len(tets), model.n_nodes))
    return connected_components(incidence @ incidence.T)[1]


def random_path(rng, size=SIZE, x=None) -> CutPath:
    """A planar cut right through the box: the blade spans its height and crosses it along y,
    tilted at random about y and z, at x (default: a random place along x)."""
    x = rng.uniform(0.3, 0.7) * size[0] if x is None else x
    tilt = np.radians(rng.uniform(-30, 30))
    turn = np.radians(rng.uniform(-30, 30))
    direction = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    top = np.array([x, -0.2 * size[1], 1.2 * size[2]])
    along = np.array([np.sin(turn), np.cos(turn), 0.0])
    return CutPath(points=[top, top + 1.5 * size[1] / np.cos(turn) * along], direction=direction,
                   depth=1.6 * size[2] / np.cos(tilt))


def cut_in_steps(cutter: Cutter, path: CutPath, steps: int, each=None):
    reports = []
    for i in range(steps):
        reports.append(cutter.cut(path.sweep(path.length * i / steps, path.length * (i + 1) / steps)))
        if each is not None:
            each(i)
    return reports


# ---- the surface ------------------------------------------------------------------------------


def test_swept_surface_crossings_and_distances():
    path = CutPath(points=[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]], direction=[0, 0, -2], depth=2.0)
    assert path.length == pytest.approx(2.0)
    np.testing.assert_allclose(path.blade(1.5), [[1.0, 0.5, 1.0], [1.0, 0.5, -1.0]])
    surface = CutSurface()
    surface.add(path.sweep(0.0, 1.5))          # the plane y = 0 for x in [0, 1], then x = 1 up to y = 0.5
    assert len(surface) == 4
    a = np.array([[0.25, -1.0, 0.0], [0.5, 1.0, 0.5], [0.5, -1.0, 2.0], [0.5, 0.2, 0.0], [0.0, 0.75, 0.0]])
    b = np.array([[0.25, 3.0, 0.0], [0.5, -1.0, 0.5], [0.5, 1.0, 2.0], [1.5, 0.2, 0.0], [2.0, 0.75, 0.0]])
    t, _ = surface.crossings(a, b)
    np.testing.assert_allclose(t[:2], [0.25, 0.5])
    assert np.isnan(t[2])                       # above the blade
    assert t[3] == pytest.approx(0.5)           # through the second piece, x = 1
    assert np.isnan(t[4])                       # beyond where the blade has gone (y 0.75 > 0.5)
    d, side, _ = surface.distances(np.array([[0.5, 0.3, 0.0], [0.5, -0.2, 0.0], [0.5, 0.0, 1.5], [1.0, 0.8, 0.0]]))
    np.testing.assert_allclose(d, [0.3, 0.2, 0.5, 0.3])
    assert side[0] == -side[1]
    np.testing.assert_allclose(sweep([[0, 0, 0], [0, 0, -1]], [[1, 0, 0], [1, 0, -1]])[:, :, 1], 0.0)


def test_distances_against_sampled_triangles():
    """Point-to-surface distances against the nearest of many points sampled on the triangles:
    never above it, and below it by at most the samples' spacing."""
    rng = np.random.default_rng(2)
    triangles = rng.uniform(-1, 1, (6, 3, 3))
    surface = CutSurface()
    surface.add(triangles)
    u, v = np.meshgrid(np.linspace(0, 1, 121), np.linspace(0, 1, 121))
    u, v = u[u + v <= 1], v[u + v <= 1]
    samples = (triangles[:, None, 0] + u[None, :, None] * (triangles[:, None, 1] - triangles[:, None, 0])
               + v[None, :, None] * (triangles[:, None, 2] - triangles[:, None, 0])).reshape(-1, 3)
    spacing = 2.0 * np.sqrt(2) / 120 * np.abs(triangles).max()
    points = rng.uniform(-1.5, 1.5, (40, 3))
    distance, _, _ = surface.distances(points)
    sampled = np.linalg.norm(points[:, None] - samples[None], axis=2).min(axis=1)
    assert np.all(distance <= sampled + 1e-12)
    assert np.all(distance >= sampled - spacing)


def test_vectorised_queries_match_numpy():
    """The planner's shortcuts against the plain numpy they replace: row-wise unique (rows, inverse,
    counts) and the elements whose bounding box meets a box."""
    from tissue.cutting.cutter import _boxes_meeting, _unique_rows

    rng = np.random.default_rng(0)
    rows = np.sort(rng.integers(0, 30, size=(400, 3)), axis=1)
    got = _unique_rows(rows, 30, return_inverse=True, return_counts=True)
    want = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w.reshape(g.shape))
    assert _unique_rows(np.zeros((0, 2), np.int64), 5).shape == (0, 2)
    x = rng.uniform(-1, 1, size=(200, 3))
    tets = rng.integers(0, 200, size=(500, 4))
    lo, hi = np.array([-0.2, -0.5, 0.0]), np.array([0.3, 0.1, 0.4])
    corners = x[tets]
    want = np.flatnonzero((corners.min(axis=1) <= hi).all(axis=1) & (corners.max(axis=1) >= lo).all(axis=1))
    np.testing.assert_array_equal(_boxes_meeting(x, tets, lo, hi), want)
    assert 0 < len(want) < len(tets)
    surface = CutSurface()
    surface.add(rng.uniform(-1, 1, size=(60, 1, 3)) + rng.uniform(-0.1, 0.1, size=(60, 3, 3)))
    points = rng.uniform(-1.2, 1.2, size=(300, 3))
    everywhere = surface.distances(points)
    for reach in (0.0, 0.05, 0.2, 5.0):          # the triangles near the points, else all: the same answer
        for got, want in zip(surface.distances_near(points, reach), everywhere):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("states", [(1, -1, -1, -1), (1, 1, -1, -1), (1, -1, 0, 0), (1, 1, -1, 0), (-1, 1, 0, 1)])
def test_split_pieces_fill_the_element(states):
    """Every sign pattern: the pieces are positive, fill the element's volume exactly, lie on their
    side, and the cut triangles are shared by the two sides."""
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.1], [0.3, 0.2, 1.0]])
    nodes = np.array([0, 1, 2, 3])
    cut, points = {}, [*rest]
    rng = np.random.default_rng(sum(states) + 7)
    for i in range(4):
        for j in range(i + 1, 4):
            if states[i] * states[j] < 0:
                cut[(i, j)] = len(points)
                points.append(rest[i] + rng.uniform(0.3, 0.7) * (rest[j] - rest[i]))
    points = np.array(points)
    tets, sides, triangles = split_element(nodes, np.array(states), cut, points)
    volumes = signed_volumes(points, tets)
    assert (volumes > 0).all()
    assert volumes.sum() == pytest.approx(signed_volumes(rest, nodes[None])[0], rel=1e-12)
    for tet, side in zip(tets, sides):
        own = [n for n in tet if n < 4]
        assert all(states[n] in (side, 0) for n in own)
    for tri in triangles:
        holders = {s for tet, s in zip(tets, sides) if set(tri) <= set(tet)}
        assert holders == {1, -1}


# ---- the cut on a body -------------------------------------------------------------------------


def test_a_full_cut_separates_the_box_and_keeps_its_volume(backend):
    model = BodyModel(box(size=SIZE, cells=(5, 2, 2)), MATERIAL)
    volume = model.volumes.sum()
    cutter = Cutter(model)
    path = CutPath(points=[[0.047, -0.01, 0.05], [0.049, 0.05, 0.05]], direction=[0, 0, -1], depth=0.1)
    reports = cut_in_steps(cutter, path, 8)
    assert sum(r.split for r in reports) > 0 and sum(r.separated for r in reports) > 0
    assert len(np.unique(pieces(model))) == 2
    assert model.volumes.sum() == pytest.approx(volume, rel=1e-12)
    centres = model.points[model.tets].mean(axis=1)[:, 0]
    label = pieces(model)
    assert {tuple(np.unique(label[centres < 0.04])), tuple(np.unique(label[centres > 0.06]))} == {(0,), (1,)}
    faces = model.boundary_faces()
    assert cutter.cut_faces().sum() > 0 and len(faces) > 0


def test_a_partial_cut_does_not_separate(backend):
    """The blade stops halfway across: the body stays in one piece (the crack front holds)."""
    model = BodyModel(box(size=SIZE, cells=(5, 2, 2)), MATERIAL)
    cutter = Cutter(model)
    path = CutPath(points=[[0.047, -0.01, 0.05], [0.049, 0.05, 0.05]], direction=[0, 0, -1], depth=0.1)
    for i in range(4):
        cutter.cut(path.sweep(path.length * i / 8, path.length * (i + 1) / 8))
    assert len(np.unique(pieces(model))) == 1
    assert sum(r.separated for r in cutter.reports) > 0       # it did open behind the front


@pytest.mark.parametrize("seed, cells", [(0, (4, 2, 2)), (1, (3, 2, 2)), (2, (4, 3, 2))])
def test_compliance_matches_the_direct_inverse_after_every_cut_step(backend, seed, cells):
    rng = np.random.default_rng(seed)
    model = BodyModel(box(size=SIZE, cells=cells), MATERIAL)
    model.set_held(np.flatnonzero(model.points[:, 0] == 0.0))
    updates = compliances(model)
    cutter = Cutter(model)

    def check(step):
        for update in updates.values():
            update.update()
        reference = direct_inverse(model)
        for mode, update in updates.items():
            error = relative_error(update.dense(), reference)
            assert error < TOLERANCE, f"{mode} after cut step {step}: relative error {error:.2e}"

    reports = cut_in_steps(cutter, random_path(rng), 5, check)
    assert sum(r.created for r in reports) > 0


def test_mass_is_density_times_the_remaining_volume(backend):
    model = BodyModel(box(size=SIZE, cells=(4, 2, 2)), MATERIAL)
    cutter = Cutter(model)
    cut_in_steps(cutter, random_path(np.random.default_rng(3)), 4)
    assert model.mass.sum() == pytest.approx(MATERIAL.density * np.prod(SIZE), rel=1e-12)
    label = pieces(model)
    assert len(np.unique(label)) == 2
    model.remove_elements(np.flatnonzero(label == label[np.argmax(model.points[model.tets].mean(axis=1)[:, 0])]))
    remaining = model.volumes.sum()
    assert remaining < 0.8 * np.prod(SIZE)
    assert model.mass.sum() == pytest.approx(MATERIAL.density * remaining, rel=1e-12)


def test_created_elements_stay_within_the_quality_bound(backend):
    """Many random cuts on a coarse box, passing within a millimetre of a plane of nodes (where a
    naive split makes slivers): every element a cut creates has its smallest dihedral angle
    ≥ MIN_DIHEDRAL and condition number ≤ MAX_CONDITION, and each cut separates the box in two;
    the naive split (no snapping) of the same cuts does go below the bound."""
    rng = np.random.default_rng(11)
    naive_worst, created = 90.0, 0
    for trial in range(12):
        model, naive_model = (BodyModel(box(size=SIZE, cells=(5, 2, 2)), MATERIAL) for _ in range(2))
        cutter, naive = Cutter(model), Cutter(naive_model, snap=0.0)
        path = random_path(rng, x=0.02 * rng.integers(2, 4) + rng.uniform(-1e-3, 1e-3))
        for i in range(4):
            patch = path.sweep(path.length * i / 4, path.length * (i + 1) / 4)
            report = cutter.cut(patch)
            assert report.min_dihedral >= MIN_DIHEDRAL and report.max_condition <= MAX_CONDITION
            created += report.created
            naive_worst = min(naive_worst, naive.cut(patch).min_dihedral)
        assert len(np.unique(pieces(model))) == 2, f"trial {trial}"
        tets = model.tets
        assert (min_dihedral_angles(model.points, tets) >= MIN_DIHEDRAL).all()
        assert (condition_numbers(model.points, tets) <= MAX_CONDITION).all()
    assert created > 100
    assert naive_worst < MIN_DIHEDRAL, naive_worst


def test_a_cut_off_piece_falls_freely(backend):
    """A bar held at x = 0, cut right through at mid-length: the free half falls as a rigid body
    under gravity (its centre of mass by g (t² + t h) / 2, implicit Euler's own fall), while the
    held half stays where it hung."""
    from tissue.fem import CorotationalFEM, Material
    from tissue.solver import ImplicitEuler
    from tissue.solver.parameters import CGSettings

    mesh = box(size=SIZE, cells=(5, 2, 2))
    fem = CorotationalFEM(mesh, Material(young=1e5, poisson=0.35, density=1000.0), rotation="polar")
    g, h = 9.81, 0.01
    solver = ImplicitEuler(fem, dt=h, gravity=(0.0, 0.0, -g), rayleigh_mass=0.0, rayleigh_stiffness=0.01,
                           cg=CGSettings(max_iterations=200, tolerance=1e-12, preconditioner="jacobi"),
                           fixed=np.flatnonzero(mesh.points[:, 0] == 0.0))
    for _ in range(10):                                     # cut where it sagged
        solver.step()
    assert np.abs(solver.positions() - mesh.points).max() > 1e-3
    cutter = Cutter(fem.model, solver)
    path = CutPath(points=[[0.05, -0.05, 0.2], [0.05, 0.05, 0.2]], direction=[0, 0, -1], depth=0.4)
    cut_in_steps(cutter, path, 3)
    model = fem.model
    label = pieces(model)
    assert len(np.unique(label)) == 2
    centres = model.points[model.tets].mean(axis=1)[:, 0]
    free_nodes = np.unique(model.tets[label == label[np.argmax(centres)]])
    held_nodes = np.unique(model.tets[label == label[np.argmin(centres)]])
    mass = model.mass[free_nodes]
    x0, v0 = solver.positions()[free_nodes], solver.velocities()[free_nodes]
    held_x0 = solver.positions()[held_nodes]
    com0, p0 = mass @ x0 / mass.sum(), mass @ v0 / mass.sum()
    steps = 20
    for _ in range(steps):
        solver.step()
    t = steps * h
    com = mass @ solver.positions()[free_nodes] / mass.sum()
    expected = com0 + p0 * t + np.array([0.0, 0.0, -g * (t * t + t * h) / 2.0])
    np.testing.assert_allclose(com, expected, atol=1e-6 * g * t * t)
    assert np.abs(solver.positions()[held_nodes] - held_x0).max() < 0.05 * g * t * t / 2


def test_cut_mesh_written_to_vtu_reads_back(backend, tmp_path):
    from tissue.mesh import read_mesh
    from tissue.mesh.io import write_vtu

    model = BodyModel(box(size=SIZE, cells=(4, 2, 2)), MATERIAL)
    cut_in_steps(Cutter(model), random_path(np.random.default_rng(5)), 4)
    mesh = model.mesh()
    write_vtu(tmp_path / "cut.vtu", mesh.points, mesh.tets)
    back = read_mesh(tmp_path / "cut.vtu")
    assert back.n_tets == model.n_elements and back.n_points == model.n_nodes
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_allclose(back.volumes, model.volumes, rtol=1e-12)


@pytest.mark.parametrize("compliance", ["warped", "exact"])
def test_cutting_a_block_resting_in_contact(backend, compliance):
    """A soft block resting on a plane is cut in two while in contact: after every step no
    constraint row names a node outside the body or off its current surface, nothing is NaN, the
    block does not sink into the plane, and once settled the two halves' contact forces carry the
    whole weight. Warped: the contact stage reads A₀⁻¹ from the cutting compliance (lazy)."""
    from test_contact import G, block, make_solver, on_plane

    from tissue.cutting import CuttingCompliance
    from tissue.fem.model import DETACHED

    solver = make_solver(block(), dt=0.01, rayleigh_mass=1.0, rayleigh_stiffness=0.01, cg_tolerance=1e-10)
    stage = on_plane(solver, friction=0.5, compliance=compliance, tolerance=1e-10)
    cutting = CuttingCompliance(solver.model, 0.01, 1.0, 0.01, fold_rank=200)
    if compliance == "warped":
        stage.follow_compliance(0, cutting)
    cutter = Cutter(solver.model, solver, cutting)
    path = CutPath(points=[[0.012, -0.07, 0.1], [0.014, 0.07, 0.1]], direction=[0, 0, -1], depth=0.2)
    weight = solver.model.mass.sum() * G
    for step in range(60):
        solver.step()
        result = stage.step()
        if 10 <= step < 16:
            cutter.cut(path.sweep(path.length * (step - 10) / 6, path.length * (step - 9) / 6))
        rows = result.rows
        assert rows is not None and rows.n_contacts > 0
        nodes = result.contacts.nodes.reshape(-1)
        assert nodes.max() < solver.model.n_nodes and (solver.model.held[nodes] != DETACHED).all()
        surface = np.unique(stage.detector.faces[0])
        assert np.isin(nodes, surface).all()
        x = solver.positions()
        assert np.isfinite(x).all() and np.isfinite(result.impulses).all()
        assert x[:, 2].min() > -1e-6
    assert len(np.unique(pieces(solver.model))) == 2
    surface = {tuple(sorted(f)) for f in stage.detector.faces[0].tolist()}
    assert surface == {tuple(sorted(f)) for f in solver.model.boundary_faces().tolist()}
    assert sum(r.split for r in cutter.reports) > 0
    assert result.contact_forces[:, 2].sum() == pytest.approx(weight, rel=2e-3)


@pytest.mark.parametrize("blas", [None, False])
def test_contact_reads_only_the_rows_it_needs_of_the_lazy_compliance(backend, blas):
    """After a cut the contact stage reads A₀⁻¹ from the lazy cutting compliance without folding
    it: the touched nodes' rows of C − T Uᵀ, gathered. The W it builds and the correction it applies
    equal h (H R) A⁻¹ (H R)ᵀ and x += R h A⁻¹ (H R)ᵀ λ with A⁻¹ the direct inverse of the cut
    body's rest matrix (1e-8 relative); a later step that finds the factors as they were folds them.
    blas False: the gather in the kernel (other archs), into the contact's ndarray."""
    import scipy.linalg
    import scipy.sparse as sp
    from test_contact import block, make_solver, on_plane

    from tissue.cutting import CuttingCompliance
    from tissue.solver.reference import rest_matrix

    dt, alpha_m, alpha_k = 0.01, 1.0, 0.01
    solver = make_solver(block(), dt=dt, rayleigh_mass=alpha_m, rayleigh_stiffness=alpha_k, cg_tolerance=1e-10)
    stage = on_plane(solver, friction=0.5, tolerance=1e-10)
    cutting = CuttingCompliance(solver.model, dt, alpha_m, alpha_k, fold_rank=200, blas=blas)
    stage.follow_compliance(0, cutting)
    cutter = Cutter(solver.model, solver, cutting)
    path = CutPath(points=[[0.012, -0.07, 0.1], [0.014, 0.07, 0.1]], direction=[0, 0, -1], depth=0.2)
    for _ in range(5):
        solver.step()
        stage.step()
    assert cutter.cut(path.sweep(0.0, path.length / 3)).nodes_added > 0
    solver.step()
    x_free = solver.positions()
    result = stage.step()
    compliance = stage.compliance[0]
    assert cutting.rank > 0 and compliance.C0 is not cutting.C        # read as rows, not folded

    model = solver.model
    n = model.n_nodes
    A = rest_matrix(model.mesh(), solver.fem.material, dt, alpha_m, alpha_k)
    free = np.flatnonzero(np.repeat(model.held == 0, 3))
    inverse = np.zeros(A.shape)
    inverse[np.ix_(free, free)] = scipy.linalg.inv(A[free][:, free].toarray())
    HR = result.rows.body_matrix(0, n) @ sp.block_diag(list(compliance.nodal_rotations()))
    W = dt * HR @ (HR @ inverse).T
    assert result.rows.n_contacts > 0
    assert np.abs(result.W - W).max() <= 1e-8 * np.abs(W).max()
    dx = dt * (sp.block_diag(list(compliance.nodal_rotations())) @ (inverse @ (HR.T @ result.impulses)))
    moved = (solver.positions() - x_free).reshape(-1)
    assert np.abs(moved).max() > 0
    assert np.abs(moved - dx).max() <= 1e-8 * np.abs(dx).max()

    solver.step()
    stage.step()                        # the factors as the last step read them: folded
    assert cutting.rank == 0 and compliance.C0 is cutting.C
