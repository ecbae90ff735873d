"""The two-level preconditioner (tissue.solver.multigrid) against independent references: its
matrix, built column by column from unit vectors, checked symmetric positive definite with numpy;
its V-cycle against the same V-cycle written densely in numpy from the scipy reference matrix;
PCG with it against the scipy direct solve (test_solver's DEFAULT_CONFIGS, and the Vulkan run there);
its iteration counts against block-Jacobi's on a slender stiff beam."""

import numpy as np
import pytest
import scipy.linalg
import taichi as ti

from test_solver import BEAM, FIXED, MATERIAL, STEP, cantilever_tip, make_solver, rel, standard_state
from tissue import compilation
from tissue.errors import TissueError
from tissue.fem import CorotationalFEM, Material
from tissue.solver import CGSettings, ImplicitEuler
from tissue.solver import reference as ref


def test_preconditioner_is_symmetric_positive_definite(solver):
    """Reference: numpy's symmetric eigensolver. The preconditioner B of a step from a state turned
    by 1.5 rad with 2 cm random strain (so element and nodal rotations differ from node to node),
    applied to every unit vector of the free dofs, is symmetric to round-off (measured 2e-16
    relative) and positive definite (smallest eigenvalue measured 0.02 of the largest 4.3)."""
    sim = solver(execution="parallel", preconditioner="multigrid")   # shared with test_solver
    x0, v0 = standard_state(1)
    sim.set_state(x0, v0)
    sim.step()
    n = BEAM.n_points
    free = ref.free_dofs(n, FIXED)
    unit = np.eye(3 * n)
    B = np.stack([sim.multigrid.apply_numpy(unit[i].reshape(n, 3)).reshape(-1)[free] for i in free], axis=1)
    assert np.abs(B - B.T).max() <= 1e-13 * np.abs(B).max()
    eigenvalues = np.linalg.eigvalsh(0.5 * (B + B.T))
    assert eigenvalues.min() > 1e-3 * eigenvalues.max()


@pytest.mark.parametrize("execution", ["parallel", "serial"])
def test_v_cycle_equals_its_dense_form(solver, execution):
    """Reference: the V-cycle z = S r, z += R P C Pᵀ Rᵀ (r - A z), z += S (r - A z) in dense numpy,
    with A the scipy reference's step matrix at the step's start (tissue.solver.reference), D its
    3×3 diagonal blocks, S Chebyshev in D⁻¹A with the multigrid's coefficients, and the kernel's own
    inputs for the rest (P's weights, the coarse inverse C, the nodal rotations R). On the free dofs
    it agrees to round-off (measured 1e-15 relative; the coarse product's order of summation is
    the kernel's own, so this bounds any reordering of it too)."""
    sim = solver(execution=execution, preconditioner="multigrid")
    x0, v0 = standard_state(2)
    sim.set_state(x0, v0)
    sim.step()
    mg, n = sim.multigrid, BEAM.n_points
    free = ref.free_dofs(n, FIXED)
    A = ref.linearise(BEAM, MATERIAL, x0, v0, STEP["dt"], rotation="large", rayleigh_mass=STEP["rayleigh_mass"],
                      rayleigh_stiffness=STEP["rayleigh_stiffness"]).A.toarray()[np.ix_(free, free)]
    blocks = [A[i:i + 3, i:i + 3] for i in range(0, len(free), 3)]
    D_inverse = scipy.linalg.block_diag(*[np.linalg.inv(b) for b in blocks])
    nodes, weights = mg.arrays["nodes"].to_numpy()[:n], mg.arrays["weights"].to_numpy()[:n]
    P = np.zeros((n, mg.n_coarse))
    np.add.at(P, (np.repeat(np.arange(n), 4), nodes.ravel()), weights.ravel())
    R = scipy.linalg.block_diag(*mg.arrays["nodal_R"].to_numpy()[:n])
    RP = (R @ np.kron(P, np.eye(3)))[free]
    coarse = RP @ mg.arrays["coarse_inverse"].to_numpy() @ RP.T

    def smooth(res):
        d = D_inverse @ res / mg.theta
        z = d.copy()
        for momentum, step in mg.steps:
            res = res - A @ d
            d = momentum * d + step * (D_inverse @ res)
            z += d
        return z

    r = np.random.default_rng(3).standard_normal(3 * n)
    r[np.setdiff1d(np.arange(3 * n), free)] = 0.0
    r_free = r[free]
    z = smooth(r_free)
    z = z + coarse @ (r_free - A @ z)
    z = z + smooth(r_free - A @ z)
    got = mg.apply_numpy(r.reshape(n, 3)).reshape(-1)
    assert np.abs(got[free] - z).max() <= 1e-12 * np.abs(z).max()


def test_multigrid_needs_far_fewer_iterations_on_a_slender_beam(backend):
    """Reference: the stiff quasi-static cantilever of test_solver (40 cells along, 410 nodes,
    condition number ~10⁵) solved to ‖r‖/‖b‖ ≤ 1e-10 with block-Jacobi and with multigrid: both
    equal the scipy static solve to 1e-8, and multigrid needs at most a tenth of Jacobi's
    iterations."""
    w_jac, w_static, it_jac, _ = cantilever_tip(40, "jacobi")
    w_mg, _, it_mg, _ = cantilever_tip(40, "multigrid")
    assert w_jac == pytest.approx(w_static, rel=1e-8)
    assert w_mg == pytest.approx(w_static, rel=1e-8)
    assert it_mg <= it_jac / 10


def test_multigrid_on_more_coarse_nodes_than_the_body_resolves(backend):
    """A thin beam of 28 nodes under a coarse grid of ~60 nodes: several coarse nodes span the same
    few fine nodes, so the Galerkin matrix Pᵀ A₀ P is singular (Cholesky fails on it) and the
    coarse correction takes its pseudo-inverse. Reference: scipy's direct solve of the same step;
    PCG still converges to it (1e-9) from a turned and strained state."""
    from tissue.mesh import beam

    mesh = beam(1.0, 0.1, 0.1, cells_along=6, cells_across=1)
    fixed = np.flatnonzero(mesh.points[:, 0] < 1e-12)
    sim = make_solver(mesh=mesh, fixed=fixed, execution="serial",
                      cg=CGSettings(max_iterations=500, tolerance=1e-12, preconditioner="multigrid", coarse_nodes=60))
    assert sim.multigrid.n_coarse > mesh.n_points - len(fixed)   # P has more columns than free rows
    x0, v0 = standard_state(3, mesh)
    sim.set_state(x0, v0)
    sim.step()
    x_ref, _ = ref.reference_step(mesh, MATERIAL, x0, v0, fixed=fixed, rotation="large", **STEP)
    assert rel(sim.positions(), x_ref) < 1e-9



def test_block_jacobi_in_one_thread_is_the_v_cycle_without_its_coarse_space(solver):
    """Block-Jacobi on the serial path runs the multigrid scheme's step kernel, its V-cycle cut to
    one smoothing of degree 1 with θ = 1 (multigrid.BlockJacobi). After a serial multigrid solver it
    compiles nothing. Reference: preconditioned CG written in numpy on the scipy reference's step
    matrix and right-hand side, z = D⁻¹ r with D its 3×3 diagonal blocks: 8 iterations from the same
    turned and strained state agree to round-off (measured 1.4e-15 relative to the largest entry,
    as the parallel path's own Jacobi branch; the multigrid's V-cycle lands 0.03 from it, no
    preconditioner 0.15)."""
    solver(execution="serial", preconditioner="multigrid").step()      # shared with the tests above
    start = compilation.count()
    sim = make_solver(execution="serial", cg=CGSettings(max_iterations=8, tolerance=0.0, preconditioner="jacobi"))
    x0, v0 = standard_state(4)
    sim.set_state(x0, v0)
    sim.step()
    dv = (sim.velocities() - v0).reshape(-1)
    assert compilation.count() == start, "block-Jacobi compiled a step kernel of its own"

    n = BEAM.n_points
    free = ref.free_dofs(n, FIXED)
    system = ref.linearise(BEAM, MATERIAL, x0, v0, STEP["dt"], gravity=STEP["gravity"], rotation="large",
                           rayleigh_mass=STEP["rayleigh_mass"], rayleigh_stiffness=STEP["rayleigh_stiffness"])
    A, b = system.A.toarray()[np.ix_(free, free)], system.b[free]
    D_inverse = scipy.linalg.block_diag(*[np.linalg.inv(A[i:i + 3, i:i + 3]) for i in range(0, len(free), 3)])
    x, r = np.zeros_like(b), b.copy()
    z = D_inverse @ r
    p, rz = z.copy(), r @ z
    for _ in range(8):
        q = A @ p
        alpha = rz / (p @ q)
        x, r = x + alpha * p, r - alpha * q
        z = D_inverse @ r
        p, rz = z + (r @ z) / rz * p, r @ z
    assert np.abs(dv[free] - x).max() <= 1e-12 * np.abs(x).max()

@pytest.mark.parametrize("kwargs,name", [(dict(coarse_nodes=4), "coarse_nodes"), (dict(coarse_nodes=1.5e3), "coarse_nodes"),
                                         (dict(smoothing_degree=0), "smoothing_degree")])
def test_multigrid_settings_are_checked(kwargs, name):
    with pytest.raises(TissueError, match=name):
        CGSettings(preconditioner="multigrid", **kwargs)


def test_multigrid_refuses_the_matrix_free_operator(backend):
    """The smoother multiplies by the assembled block rows, which matrix-free mode does not keep."""
    with pytest.raises(TissueError, match="multigrid"):
        ImplicitEuler(CorotationalFEM(BEAM, Material(1e5, 0.3, 1000.0)), 0.01, operator="matrix_free",
                      cg=CGSettings(preconditioner="multigrid"))


def test_nodal_rotation_where_the_element_rotations_cancel(backend):
    """A node between an unturned element and one turned by a half turn about x (as in the
    mirrored half of tests/test_stability.py): the mean of the two rotations, diag(1, 0, 0), has no
    polar factor (before, the scaled Newton iteration returned NaN, and the multigrid's coarse
    correction with it: the CG stopped at its first iteration). The node takes a proper rotation
    of its elements; an ordinary node still gets the orthonormalised mean."""
    import taichi as ti

    from tissue.contact.warping import _nodal_rotations

    half_turn = np.diag([1.0, -1.0, -1.0])
    c, s = np.cos(0.3), np.sin(0.3)
    turned = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    Re = np.stack([np.eye(3), half_turn, turned, turned])
    incidence = np.array([[0, 4, -1], [8, 12, -1], [-1, -1, -1]], dtype=np.int32)   # element e at 4 e + corner
    valence = np.array([2, 2, 0], dtype=np.int32)
    arrays = [ti.ndarray(ti.types.matrix(3, 3, ti.f64), 4), ti.ndarray(ti.i32, 3), ti.ndarray(ti.i32, (3, 3)),
              ti.ndarray(ti.types.matrix(3, 3, ti.f64), 3)]
    for a, values in zip(arrays, (Re, valence, incidence)):
        a.from_numpy(values)
    _nodal_rotations(*arrays, 1e-12)
    R = arrays[3].to_numpy()
    assert np.isfinite(R).all()
    assert any(np.allclose(R[0], r, atol=1e-12) for r in Re[:2])
    assert np.allclose(R[1], turned, atol=1e-12)
    assert np.allclose(R[2], np.eye(3))


def test_nodal_rotations_are_shared_while_current(solver):
    """The solver hands out the multigrid's nodal rotations of its last step (the warped contact
    compliance reads them instead of computing its own) equal bit for bit to the compliance's own
    kernel on the FEM's element rotations, and only while they are those rotations' and at the
    tolerance asked: not after the element rotations were written by another launch (or a launch
    of the step's taken without recording it), nor after a rebuild, until the next step."""
    from tissue.contact.warping import _nodal_rotations

    sim = solver(execution="parallel", preconditioner="multigrid")
    tol = sim.fem.rotation_tolerance
    x0, v0 = standard_state(1)
    sim.set_state(x0, v0)
    sim.step()
    shared = sim.nodal_rotations(tol)
    assert shared is sim.multigrid.arrays["nodal_R"]
    assert sim.nodal_rotations(2 * tol) is None
    own = ti.Matrix.ndarray(3, 3, ti.f64, shared.shape)
    _nodal_rotations(sim.fem.R, *sim.fem.model.gather_index(), own, tol)
    assert np.array_equal(own.to_numpy(), shared.to_numpy())
    sim.fem.rotations_numpy(x0)
    assert sim.nodal_rotations(tol) is None
    sim.step()
    assert sim.nodal_rotations(tol) is not None
    sim.prepare_step()                      # a launch of the step's own (unrecorded) may follow
    assert sim.nodal_rotations(tol) is None
    sim.step()
    assert sim.nodal_rotations(tol) is not None
    sim.multigrid.rebuild()
    assert sim.nodal_rotations(tol) is None


def test_a_return_to_an_earlier_dt_reuses_its_set_up(backend, monkeypatch):
    """The energy check takes a rejected step as two of dt/2 and goes back to dt
    (tissue.solver.step_control): the multigrid keeps each dt's coarse inverse and Chebyshev
    coefficients (Multigrid.retune), so going back and forth makes the rest matrix once per dt, and
    keeps the last step's nodal rotations. Reference: a solver built at each dt, whose set-up equals
    the live one's bit for bit, as does its step from the same state."""
    from tissue.solver import implicit_euler

    sim = make_solver(execution="serial", preconditioner="multigrid")
    made = []
    original = implicit_euler.rest_matrix
    monkeypatch.setattr(implicit_euler, "rest_matrix", lambda *args: made.append(args[2]) or original(*args))
    dt = STEP["dt"]
    for h in (dt / 2, dt, dt / 2, dt):
        sim.set_parameters(dt=h)
        fresh = make_solver(execution="serial", preconditioner="multigrid", **{**STEP, "dt": h})
        for name in ("coarse_inverse", "coefficients"):
            assert np.array_equal(sim.multigrid.arrays[name].to_numpy(), fresh.multigrid.arrays[name].to_numpy())
        x0, v0 = standard_state(1)
        for s in (sim, fresh):
            s.set_state(x0, v0)
            s.step()
        assert np.array_equal(sim.positions(), fresh.positions())
    assert made.count(dt / 2) == 1 + 2 and made.count(dt) == 2     # the live solver's one, the fresh ones'
    tol = sim.fem.rotation_tolerance
    shared = sim.nodal_rotations(tol)
    sim.set_parameters(dt=dt / 2)           # the element rotations unchanged: their nodal ones still current
    assert shared is not None and sim.nodal_rotations(tol) is shared
