"""CG warm-started from the last solves and corrections (CGSettings.warm_start,
tissue.solver.warm_start) against references it did not produce: the scipy direct solve of the same linearised step and its residual (tissue.solver.reference),
and free fall in closed form. A warm start changes where CG starts, not where it stops."""

from dataclasses import replace

import numpy as np
import pytest

from test_solver import BEAM, DEFAULT_CONFIGS, FIXED, MATERIAL, STEP, make_solver, rel, standard_state
from tissue.errors import TissueError
from tissue.fem import Material
from tissue.mesh import box
from tissue.solver import CGSettings
from tissue.solver import reference as ref

# One of each path the start takes: the serial step's symmetric product, the parallel rows, the
# matrix-free product (atomic, Jacobi), the multigrid's coupled preconditioner; the matrix-free
# parallel product in the slow run.
CONFIGS = [c for c in DEFAULT_CONFIGS if c[0] == "large"] + [
    pytest.param(("large", "gather", "parallel", "matrix_free", "none"), marks=pytest.mark.slow)]


def steps_with(sim, warm_start, tolerance, steps, x0, v0):
    """`steps` steps from (x0, v0) with this CG start and tolerance: the state before each step,
    the state after the last, and the CG iterations and reported residual of each."""
    settings = sim.cg
    sim.set_parameters(cg=replace(settings, warm_start=warm_start, tolerance=tolerance))
    try:
        sim.set_state(x0, v0)
        states = []
        for _ in range(steps):
            states.append((sim.positions(), sim.velocities()))
            sim.step()
        states.append((sim.positions(), sim.velocities()))
        history = sim.stats.history
        return states, history["cg_iterations"][-steps:], history["cg_residual"][-steps:]
    finally:
        sim.set_parameters(cg=settings)


def true_residual(before, after):
    """‖b − A dv‖ / ‖b‖ of a step on the free dofs, A and b assembled by the reference."""
    (x, v), (_, v_after) = before, after
    system = ref.linearise(BEAM, MATERIAL, x, v, rotation="large", **STEP)
    free = ref.free_dofs(BEAM.n_points, FIXED)
    dv = (v_after - v).reshape(-1)[free]
    b = system.b[free]
    return np.linalg.norm(b - system.A[free][:, free] @ dv) / np.linalg.norm(b)


@pytest.mark.parametrize("config", CONFIGS, ids="-".join)
def test_warm_start_stops_by_the_same_rule(solver, config):
    """Five steps from the standard state to ‖r‖ ≤ 1e-6 ‖b‖, cold and warm: every warm step meets
    that bound as the cold ones do, in the residual CG reports and in the one the reference's
    assembled A and b give (to 1e-9 beyond it: the recursively updated residual drifts from the
    true one by round-off). (Fewer iterations are not asserted: from this random state's start each
    step's dv is unlike the last; test_free_fall_starts_at_its_solution and bench/free_motion.py
    show the savings.)"""
    sim = solver(*config)
    x0, v0 = standard_state(1)
    tolerance = 1e-6
    runs = {warm: steps_with(sim, warm, tolerance, 5, x0, v0) for warm in (False, True)}
    for warm, (states, iterations, reported) in runs.items():
        assert max(reported) <= tolerance, (warm, reported)
        residuals = [true_residual(states[i], states[i + 1]) for i in range(5)]
        assert max(residuals) <= tolerance + 1e-9, (warm, residuals)


@pytest.mark.parametrize("config", CONFIGS, ids="-".join)
def test_warm_started_steps_match_the_direct_solve(solver, config):
    """Reference: scipy's sparse LU of each step's independently assembled system (as
    test_solver.test_step_matches_direct_solve), from each state of a warm-started run of four
    steps to ‖r‖ ≤ 1e-12 ‖b‖, with the held nodes changed before the third (the last solve's dv there
    is no start): the same 1e-8 as the cold steps."""
    sim = solver(*config)
    x0, v0 = standard_state(2)
    settings = sim.cg
    sim.set_parameters(cg=replace(settings, warm_start=True, tolerance=1e-12))
    held = np.flatnonzero(BEAM.points[:, 0] > 1.0 - 1e-12)      # the free end too
    try:
        sim.set_state(x0, v0)
        for step in range(4):
            fixed = FIXED if step < 2 else np.concatenate([FIXED, held])
            if step == 2:
                sim.set_fixed(fixed)
            x, v = sim.positions(), sim.velocities()
            sim.step()
            x_ref, v_ref = ref.reference_step(BEAM, MATERIAL, x, v, fixed=fixed, rotation="large", **STEP)
            assert sim.stats.counters["cg_residual"] <= 1e-12
            assert rel(sim.velocities(), v_ref) <= 1e-8
            assert rel(sim.positions() - x, x_ref - x) <= 1e-8
    finally:
        sim.set_fixed(FIXED)
        sim.set_parameters(cg=settings)


@pytest.mark.parametrize("config", CONFIGS + [("large", "gather", "serial", "assembled", "multigrid")],
                         ids="-".join)
def test_start_is_the_best_combination_of_the_last_steps(solver, config):
    """Reference: the start of least A-norm error over the span of what the warm start keeps
    (tissue.solver.warm_start), from the reference's assembled A and b in numpy. Four steps to
    1e-12 from a standard state, the free nodes' velocities kicked by 2 cm/s between steps (as a
    contact correction changes them); then a step stopped where it starts (tolerance 1e3: no CG
    iteration), whose dv is the start. D: the last solve's dv, the one before, the last kick and
    the one before. Its dv is D c with DᵀA D c = Dᵀb to 1e-8, and its error in the A-norm is no
    larger than that of the last dv alone (the plain warm start) or of zero."""
    sim = solver(*config)
    x0, v0 = standard_state(3)
    rng = np.random.default_rng(4)
    free_nodes = np.setdiff1d(np.arange(BEAM.n_points), FIXED)
    settings = sim.cg
    solves, kicks = [], []
    try:
        sim.set_parameters(cg=replace(settings, warm_start=True, tolerance=1e-12, max_iterations=300))
        sim.set_state(x0, v0)
        for _ in range(4):
            v = sim.velocities()
            sim.step()
            solves.append(sim.velocities() - v)
            kick = np.zeros_like(v)
            kick[free_nodes] = 0.02 * rng.standard_normal((len(free_nodes), 3))
            sim.set_state(velocities=sim.velocities() + kick)
            kicks.append(kick)
        x, v = sim.positions(), sim.velocities()
        sim.set_parameters(cg=replace(settings, warm_start=True, tolerance=1e3))
        sim.step()
        assert sim.stats.counters["cg_iterations"] == 0
        start = (sim.velocities() - v).reshape(-1)
    finally:
        sim.set_parameters(cg=settings)
    system = ref.linearise(BEAM, MATERIAL, x, v, rotation="large", **STEP)
    free = ref.free_dofs(BEAM.n_points, FIXED)
    A, b = system.A[free][:, free].toarray(), system.b[free]
    D = np.stack([d.reshape(-1)[free] for d in (solves[-1], solves[-2], kicks[-1], kicks[-2])], axis=1)
    best = D @ np.linalg.solve(D.T @ A @ D, D.T @ b)
    assert rel(start[free], best) <= 1e-8
    solution = np.linalg.solve(A, b)

    def error(guess):
        e = solution - guess
        return float(np.sqrt(e @ A @ e))

    assert error(start[free]) <= min(error(D[:, 0]), error(np.zeros_like(b))) * (1 + 1e-9)


def test_free_fall_starts_at_its_solution(backend):
    """A free, unstrained body with no mass damping falls with dv = h g every step (closed form: the
    elastic forces and K v of a translation vanish). Its first step is solved to 1e-14, the others
    to 1e-9: from the second step on the warm start, at this dt and scaled to a changed one, is the
    solution to the first step's residual, so CG stops with no iteration; the velocity is that of
    free fall."""
    mesh = box(size=(0.1, 0.05, 0.04), cells=(4, 2, 2))
    g = np.array([0.0, -3.0, -9.81])
    tight = CGSettings(max_iterations=200, tolerance=1e-14, warm_start=True)
    sim = make_solver(mesh=mesh, material=Material(3e3, 0.3, 1000.0), fixed=None, cg=tight,
                      dt=0.02, gravity=tuple(g), rayleigh_mass=0.0, rayleigh_stiffness=0.1)
    t = 0.0
    for dt in (0.02, 0.02, 0.02, 0.01, 0.01, 0.04):
        sim.set_parameters(dt=dt)
        sim.step()
        sim.set_parameters(cg=replace(tight, tolerance=1e-9))
        t += dt
        assert np.allclose(sim.velocities(), g * t, rtol=0, atol=1e-12 * np.linalg.norm(g) * t)
    assert sim.stats.history["cg_iterations"][0] > 0
    assert sim.stats.history["cg_iterations"][1:] == [0] * 5


def test_warm_start_must_be_a_bool():
    with pytest.raises(TissueError, match="warm_start"):
        CGSettings(warm_start=1)
