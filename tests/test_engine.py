"""The engine: kernels compiled once per process whatever the mesh, size and parameters; step
parameters changed on a live solver; topology edits of the model in place (tissue.fem.model).

References: the scipy direct solve of the same step (tissue.solver.reference), a solver built fresh
with the same settings, and a body built fresh on the edited mesh. Compilation is counted from
Taichi's kernel objects (tissue.compilation.count: compiled kernel instances in this process).
"""

import numpy as np
import pytest

from tissue import compilation
from tissue.errors import TissueError
from tissue.fem import CorotationalFEM, Material
from tissue.fem.model import DETACHED, HELD, BodyModel
from tissue.mesh import TetMesh, beam, box
from tissue.solver import CGSettings, ImplicitEuler
from tissue.solver import reference as ref

MATERIAL = Material(young=1e5, poisson=0.3, density=1000.0)
TIGHT = CGSettings(max_iterations=2000, tolerance=1e-13)


def clamped(mesh):
    return np.flatnonzero(mesh.points[:, 0] < mesh.points[:, 0].min() + 1e-12)


def strained_state(mesh, seed):
    rng = np.random.default_rng(seed)
    return mesh.points + 0.01 * rng.standard_normal(mesh.points.shape), 0.1 * rng.standard_normal(mesh.points.shape)


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_bodies_of_three_sizes_compile_once(backend):
    """Three beams of 144 to 1,080 tetrahedra with different dt, damping, gravity and CG caps,
    stepped one after another: after the first, nothing compiles; each step equals the direct solve
    (CG to 1e-13, so the result is set by the direct solve: 1e-10 relative)."""
    meshes = [beam(1.0, 0.2, 0.2, cells_along=6, cells_across=2), beam(1.0, 0.2, 0.2, cells_along=10, cells_across=3),
              beam(2.0, 0.3, 0.3, cells_along=20, cells_across=3)]
    settings = [dict(dt=0.01, gravity=(0.0, 0.0, -9.81), rayleigh_mass=0.1, rayleigh_stiffness=0.01),
                dict(dt=0.004, gravity=(0.0, -2.0, -9.81), rayleigh_mass=0.5, rayleigh_stiffness=0.0),
                dict(dt=0.02, gravity=(1.0, 0.0, -3.0), rayleigh_mass=0.0, rayleigh_stiffness=0.02)]
    caps = [CGSettings(max_iterations=3000, tolerance=1e-13), CGSettings(max_iterations=2500, tolerance=1e-13),
            CGSettings(max_iterations=4000, tolerance=1e-13, threshold=1e-40)]
    counts = []
    for i, (mesh, step, cg) in enumerate(zip(meshes, settings, caps)):
        solver = ImplicitEuler(CorotationalFEM(mesh, MATERIAL, rotation="polar"), cg=cg, fixed=clamped(mesh),
                               execution="serial", **step)
        x0, v0 = strained_state(mesh, i)
        solver.set_state(x0, v0)
        solver.step()
        x_ref, v_ref = ref.reference_step(mesh, MATERIAL, x0, v0, fixed=clamped(mesh), rotation="polar", **step)
        assert rel(solver.velocities(), v_ref) <= 1e-10, i
        assert rel(solver.positions() - x0, x_ref - x0) <= 1e-10, i
        counts.append(compilation.count())     # after reading back: Taichi's copy kernels count too
    assert counts[1] == counts[0] and counts[2] == counts[0], f"kernels compiled per body: {counts}"


@pytest.mark.parametrize("execution", ["serial", "parallel"])
def test_changed_parameters_step_as_a_fresh_solver(backend, execution):
    """dt, damping and the CG cap changed on a live solver give the next step of a solver built
    with them (1e-12), and compile nothing."""
    mesh = beam(1.0, 0.2, 0.2, cells_along=6, cells_across=2)
    before = dict(dt=0.01, rayleigh_mass=0.1, rayleigh_stiffness=0.01, cg=CGSettings(max_iterations=40))
    after = dict(dt=0.003, rayleigh_mass=0.7, rayleigh_stiffness=0.05, cg=CGSettings(max_iterations=9))
    live = ImplicitEuler(CorotationalFEM(mesh, MATERIAL), fixed=clamped(mesh), execution=execution, **before)
    x0, v0 = strained_state(mesh, 3)
    live.set_state(x0, v0)
    live.step()
    x1, v1 = live.positions(), live.velocities()
    start = compilation.count()
    live.set_parameters(**after)
    live.step()
    assert compilation.count() == start
    fresh = ImplicitEuler(CorotationalFEM(mesh, MATERIAL), fixed=clamped(mesh), execution=execution, **after)
    fresh.set_state(x1, v1)
    fresh.step()
    assert live.stats.counters["cg_iterations"] == 9 == fresh.stats.counters["cg_iterations"]
    assert np.abs(live.positions() - fresh.positions()).max() <= 1e-12 * np.abs(x1).max()
    assert np.abs(live.velocities() - fresh.velocities()).max() <= 1e-12 * max(1.0, np.abs(v1).max())


def test_live_parameters_are_validated(backend):
    mesh = box(size=(1, 1, 1), cells=(1, 1, 1))
    solver = ImplicitEuler(CorotationalFEM(mesh, MATERIAL), 0.01)
    with pytest.raises(TissueError, match="dt"):
        solver.set_parameters(dt=-1.0)
    with pytest.raises(TissueError, match="preconditioner"):
        solver.set_parameters(cg=CGSettings(preconditioner="jacobi"))
    assert solver.dt == 0.01


def edited_mesh(seed=0):
    """A 4×3×3-cell box (216 tets); 10 % of its elements removed, 2 nodes added and 4 elements
    over them (inside the removed region's holes, positively oriented)."""
    mesh = box(size=(0.4, 0.3, 0.3), cells=(4, 3, 3))
    rng = np.random.default_rng(seed)
    removed = rng.choice(mesh.n_tets, mesh.n_tets // 10, replace=False)
    # New nodes: centroids of two removed elements, each joined to its element's 4 corners.
    hosts = removed[:2]
    new_points = mesh.points[mesh.tets[hosts]].mean(axis=1)
    return mesh, removed, hosts, new_points


def split_into_four(tets, centre_ids):
    """Each tet (a, b, c, d) around its centre c: the 4 tets with one face each and the centre."""
    faces = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward, as mesh.surface
    out = []
    for t, c in zip(tets, centre_ids):
        for f in faces:
            out.append([t[f[0]], t[f[2]], t[f[1]], c])
    return np.array(out)


@pytest.mark.parametrize("execution", ["serial", "parallel"])
def test_topology_edits_step_as_a_fresh_body(backend, execution):
    """Remove 10 % of the elements, add two nodes and split two removed elements' space into 4
    each around them, on a live solver: the next step equals that of a body built fresh on the
    resulting mesh (1e-12), with no new compilation; mass follows (Σ = ρ × volume kept)."""
    mesh, removed, hosts, new_points = edited_mesh()
    fixed = clamped(mesh)
    # The edit kernels and Taichi's copy kernels compile on their first use in a process: a first
    # edit of another body (another seed) pays for that; the edit measured here must compile nothing.
    other, other_removed, other_hosts, other_points = edited_mesh(seed=1)
    warm = ImplicitEuler(CorotationalFEM(other, MATERIAL, rotation="polar"), 0.01, execution=execution)
    warm.model.remove_elements(other_removed)
    warm.model.add_elements(split_into_four(other.tets[other_hosts], warm.model.add_nodes(other_points)))
    warm.step()
    live = ImplicitEuler(CorotationalFEM(mesh, MATERIAL, rotation="polar"), 0.01, fixed=fixed, execution=execution,
                         cg=TIGHT, rayleigh_mass=0.1)
    x0, v0 = strained_state(mesh, 5)
    live.set_state(x0, v0)
    live.step()
    x_step, v_step = live.positions(), live.velocities()   # (Taichi compiles its copy kernels on first use)
    start = compilation.count()
    model = live.model
    model.remove_elements(removed)
    ids = model.add_nodes(new_points)
    model.add_elements(split_into_four(mesh.tets[hosts], ids))
    x1 = np.vstack([x_step, new_points + 0.001])
    v1 = np.vstack([v_step, np.zeros((2, 3))])
    live.set_state(x1, v1)
    live.step()
    assert compilation.count() == start, "a topology edit compiled kernels"

    edited = TetMesh(model.points.copy(), model.tets.astype(np.int64))
    assert edited.n_tets == mesh.n_tets - len(removed) + 8
    volume = edited.volumes.sum()
    assert abs(model.mass.sum() - MATERIAL.density * volume) <= 1e-12 * model.mass.sum()
    fresh = ImplicitEuler(CorotationalFEM(edited, MATERIAL, rotation="polar"), 0.01, fixed=fixed,
                          execution=execution, cg=TIGHT, rayleigh_mass=0.1)
    fresh.set_state(x1, v1)
    fresh.step()
    detached = model.held == DETACHED
    assert np.abs(live.positions() - fresh.positions())[~detached].max() <= 1e-12
    assert np.abs(live.velocities() - fresh.velocities())[~detached].max() <= 1e-12


def test_model_edits_keep_its_invariants(backend):
    """After edits: the gather index lists exactly each node's element corners, mass is Σ ρV/4,
    nodes without elements are detached (and come back when used), held nodes stay held, and
    the boundary faces are those of the remaining elements."""
    from tissue.mesh import boundary_faces

    mesh = box(size=(0.3, 0.3, 0.3), cells=(3, 3, 3))
    model = BodyModel(mesh, MATERIAL, node_capacity=mesh.n_points, element_capacity=mesh.n_tets)
    model.set_held([0, 1])
    model.boundary_faces()                            # from here on, kept by the edits
    rng = np.random.default_rng(1)
    removed = []
    for _ in range(5):
        ids = rng.choice(model.n_elements, 7, replace=False)
        removed.append(model.tets[ids].copy())
        model.remove_elements(ids)
    removed = np.concatenate(removed)
    model.add_elements(removed[:15])                  # some come back
    centres = model.add_nodes(model.points[removed[15:25]].mean(axis=1))
    model.add_elements(split_into_four(removed[15:25], centres))   # past the element capacity
    assert model.growths >= 1 and model.n_elements == mesh.n_tets - 35 + 15 + 40
    tets = model.tets
    offsets, corners = model.incidence_csr()
    for v in range(model.n_nodes):
        expected = sorted(4 * e + a for e, a in zip(*np.nonzero(tets == v)))
        assert sorted(corners[offsets[v]:offsets[v + 1]]) == expected
    mass = np.zeros(model.n_nodes)
    np.add.at(mass, tets.reshape(-1), np.repeat(MATERIAL.density * model.volumes / 4.0, 4))
    np.testing.assert_allclose(model.mass, mass, rtol=1e-12, atol=1e-15)
    unused = np.setdiff1d(np.arange(model.n_nodes), tets)
    assert (model.held[unused] == DETACHED).all()
    assert (model.held[np.setdiff1d(np.intersect1d([0, 1], tets), unused)] == HELD).all()
    got = {tuple(np.roll(f, -np.argmin(f))) for f in model.boundary_faces()}
    want = {tuple(np.roll(f, -np.argmin(f))) for f in boundary_faces(tets)}
    assert got == want


def test_edit_writes_in_place_and_equals_a_fresh_model(backend):
    """An edit within the reserved capacity (remove 10 elements, add 2 nodes, add 16 elements:
    8 back and 2 split into 4 around the new nodes) on a live solver re-allocates nothing (the
    model's, the solver's and its blocks' arrays are the same objects) and compiles nothing; the
    model then equals one built fresh on the edited mesh exactly: mass, element data, gather
    index, boundary and held nodes, in the numpy mirrors and on the device. The solver's nodes
    keep their state; the new ones start at rest, still."""
    mesh = box(size=(0.4, 0.3, 0.3), cells=(4, 3, 3))
    fixed = clamped(mesh)
    solver = ImplicitEuler(CorotationalFEM(mesh, MATERIAL), 0.01, fixed=fixed)
    model = solver.model
    model.reserve(nodes=10, elements=40)
    model.boundary_faces()                                     # from here on, kept by the edits
    rng = np.random.default_rng(3)

    def edit():
        ids = rng.choice(model.n_elements, 10, replace=False)
        tets = model.tets[ids].astype(np.int64)
        model.remove_elements(ids)
        centres = model.add_nodes(model.points[tets[:2]].mean(axis=1))
        model.add_elements(np.concatenate([tets[2:], split_into_four(tets[:2], centres)]))

    for _ in range(2):      # the edit kernels compile on first use; the blocks' pattern grows once
        edit()
    solver.step()
    x_before, v_before = solver.positions(), solver.velocities()
    stored = [solver.x, solver.v, solver.fem.work, solver.matrix.pack, model.pack, *model.arrays.values()]
    versions, start = (model.version, model.growths, solver.allocations), compilation.count()
    edit()
    assert compilation.count() == start, "an edit compiled kernels"
    assert (model.version, model.growths, solver.allocations) == versions, "an edit re-allocated"
    same = [solver.x, solver.v, solver.fem.work, solver.matrix.pack, model.pack, *model.arrays.values()]
    assert all(a is b for a, b in zip(stored, same)), "an edit replaced a storage object"
    n_old = len(x_before)
    np.testing.assert_array_equal(solver.positions()[:n_old], x_before)
    np.testing.assert_array_equal(solver.velocities()[:n_old], v_before)
    np.testing.assert_array_equal(solver.positions()[n_old:], model.points[n_old:])
    np.testing.assert_array_equal(solver.velocities()[n_old:], 0.0)

    fresh = BodyModel(TetMesh(model.points.copy(), model.tets.astype(np.int64)), MATERIAL)
    fresh.set_held(fixed)
    n, m = model.n_nodes, model.n_elements
    assert (fresh.n_nodes, fresh.n_elements) == (n, m)
    for name in ("tets", "Dm_inv", "elastic", "density", "mass", "held", "points"):
        np.testing.assert_array_equal(getattr(model, name), getattr(fresh, name), err_msg=name)
    np.testing.assert_array_equal(model._rest_frame[:m], fresh._rest_frame[:m])
    np.testing.assert_array_equal(model._valence[:n], fresh._valence[:n])
    gather = []                           # each node's corner codes, in ascending order
    for body in (model, fresh):
        offsets, corners = body.incidence_csr()
        gather.append((offsets, corners[np.lexsort((corners, np.repeat(np.arange(n), np.diff(offsets))))]))
    np.testing.assert_array_equal(gather[0][0], gather[1][0])
    np.testing.assert_array_equal(gather[0][1], gather[1][1])
    for live_model in (model, fresh):     # the device holds what the numpy mirrors hold
        device = {k: a.to_numpy() for k, a in live_model.arrays.items()}
        assert device["counts"].tolist() == [n, m]
        for name, rows in (("tets", m), ("Dm_inv", m), ("rest_frame", m), ("elastic", m), ("mass", n),
                           ("held", n), ("valence", n), ("rest", n)):
            np.testing.assert_array_equal(device[name][:rows], getattr(live_model, "_" + name)[:rows], err_msg=name)
        np.testing.assert_array_equal(device["incidence"][:n], live_model.incidence_rows[:n])
    canonical = lambda faces: {tuple(np.roll(f, -np.argmin(f))) for f in faces.tolist()}   # noqa: E731
    assert canonical(model.boundary_faces()) == canonical(fresh.boundary_faces())


def test_edits_refuse_bad_elements(backend):
    mesh = box(size=(0.3, 0.3, 0.3), cells=(1, 1, 1))
    model = BodyModel(mesh, MATERIAL)
    with pytest.raises(TissueError, match=r"tetrahedra \[0\].*inverted"):
        model.add_elements(mesh.tets[:1][:, [1, 0, 2, 3]])
    with pytest.raises(TissueError, match="out of range"):
        model.add_elements([[0, 1, 2, 999]])
    with pytest.raises(TissueError, match="out of range"):
        model.remove_elements([mesh.n_tets])
    assert model.n_elements == mesh.n_tets


def test_live_simulation_parameters_step_as_a_fresh_simulation(backend):
    """Simulation.set_parameters (dt, the CG cap, damping, gravity) on a live beam scene: the next
    step equals that of a Simulation built with those settings from the same state (1e-12), the
    clock advances by the new dt, nothing compiles; with contact, dt is refused by name."""
    import scenes
    from tissue.simulation import Simulation

    # (CG started cold: a warm start's guess is the live run's last solve, which a fresh one lacks)
    scene = scenes.load("beam")().with_overrides(["beam.cells=6,1,1", "solver.cg_warm_start=false"])
    live = Simulation(scene)
    live.run(2)
    x, v = live.bodies["beam"].positions(), live.bodies["beam"].velocities()
    start = compilation.count()
    changes = dict(dt=0.004, cg_iterations=7, rayleigh_mass=0.3, gravity=(0.0, -1.0, -9.81))
    live.set_parameters(**changes)
    live.step()
    assert compilation.count() == start
    assert live.time == pytest.approx(2 * 0.01 + 0.004, abs=1e-15)
    fresh = Simulation(scene.with_overrides(["dt=0.004", "solver.cg_iterations=7", "solver.rayleigh_mass=0.3",
                                             "gravity=0,-1,-9.81"]))
    fresh.bodies["beam"].solver.set_state(x, v)
    fresh.step()
    assert live.stats.counters["cg_iterations"] == 7
    np.testing.assert_allclose(live.bodies["beam"].positions(), fresh.bodies["beam"].positions(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(live.bodies["beam"].velocities(), fresh.bodies["beam"].velocities(), rtol=0,
                               atol=1e-12)
    with pytest.raises(TissueError, match="cg_iteration: not a parameter"):
        live.set_parameters(cg_iteration=3)
    with pytest.raises(TissueError, match="dt"):
        live.set_parameters(dt=-1.0)

    contact = Simulation(scenes.load("incline")().with_overrides(["block.cells=2,2,1"]))
    with pytest.raises(TissueError, match="dt: the contact stage"):
        contact.set_parameters(dt=0.02)
    contact.set_parameters(cg_iterations=30)
    assert contact.bodies["block"].solver.cg.max_iterations == 30
