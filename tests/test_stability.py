"""The fast cells of bench/stability.py: each stays bounded (no NaN, the energy never more than
stability.ALLOWANCE of its scale above its start plus the external work, no element left inverted)
or is refused before its first step with a message, and a non-finite state never passes silently.
(The full matrix: `python -m bench.stability`.)"""

import numpy as np
import pytest

from bench import stability
from bench.nonlinear_reference import Body, internal_forces, tangent
from tissue.errors import TissueError


def outcome(cell):
    result = stability.simulate(cell)
    assert result["outcome"] != "silent-nan", result
    if result["outcome"] == "refused":
        assert result["message"] and "steps_done" not in result, result
    return result


def test_outcomes_are_classified_by_the_stated_definitions():
    """An error during the run is a divergence, not a refusal; the energy may rise at most
    ALLOWANCE (1 %) of its scale; elements left inverted fail a cell whose energy is bounded."""
    a = stability.ALLOWANCE
    assert a == 0.01
    assert stability.classify("the simulation diverged", True, 0.0, 0) == "diverged"
    assert stability.classify(None, False, 0.0, 0) == "silent-nan"
    assert stability.classify(None, True, 0.99 * a, 0) == "bounded"
    assert stability.classify(None, True, 1.01 * a, 0) == "energy"
    assert stability.classify(None, True, 1.01 * a, 3) == "energy"
    assert stability.classify(None, True, 0.0, 3) == "inverted"


def test_bad_input_is_refused_before_the_first_step_with_its_cause():
    r = outcome(dict(case="material", young=1e4, poisson=0.5, dt=0.04, rotation="polar"))
    assert r["outcome"] == "refused" and "poisson" in r["message"].lower(), r


def test_an_error_during_the_run_is_a_divergence(backend, monkeypatch):
    """A TissueError raised by the third step (as a diverging solve raises) fails the cell as
    `diverged`, with its message; it is not counted as refused."""
    from tissue.solver import ImplicitEuler

    calls = []
    record_step = ImplicitEuler.record_step     # where a step, checked or not, reports its solve

    def failing(self, report):
        calls.append(1)
        if len(calls) == 3:
            raise TissueError("the simulation diverged at step 3 (test)")
        record_step(self, report)

    monkeypatch.setattr(ImplicitEuler, "record_step", failing)
    r = outcome(dict(case="material", young=1e5, poisson=0.3, dt=0.04, rotation="polar"))
    assert r["outcome"] == "diverged" and "diverged" in r["message"] and r["steps_done"] == 3, r


# "large" is not the scenes' rotation: its cells compile a step of their own (the multigrid's),
# so they run in the slow set; the default run checks the scenes' "polar".
LARGE = pytest.param("large", marks=pytest.mark.slow)


@pytest.mark.parametrize("rotation", [LARGE, "polar"])
def test_stiff_nearly_incompressible_huge_step_stays_bounded_or_is_refused(backend, rotation):
    r = outcome(dict(case="material", young=1e8, poisson=0.499, dt=0.5, rotation=rotation))
    assert r["outcome"] in ("bounded", "refused"), r


# A whole step with "invertible" compiles for minutes here (its eigen-solves inline in every
# kernel of the step): those cells run in the slow set; tests/test_invertible.py checks the element.
INVERTIBLE = pytest.param("invertible", marks=pytest.mark.slow)


@pytest.mark.parametrize("mode", ["smooth", "abrupt"])
@pytest.mark.parametrize("rotation", [LARGE, "polar", INVERTIBLE])
def test_half_turn_twist_stays_bounded(backend, mode, rotation):
    """("large", abrupt) gained 0.035 energy scales with the energy check alone: its forces are
    not the gradient of the polar energy, so each step gained a little under the check's
    tolerance, and the gains added up; the energy budget removes each step's gain."""
    r = outcome(dict(case="twist", mode=mode, dt=0.04, steps=150, rotation=rotation))
    assert r["outcome"] == "bounded", r


@pytest.mark.parametrize("mode", ["node", "mirror"])
@pytest.mark.parametrize("rotation", [LARGE, "polar"])
def test_inverted_initial_state_recovers(backend, mode, rotation):
    r = outcome(dict(case="inverted", mode=mode, dt=0.04, steps=250, rotation=rotation))
    assert r["inverted_at_start"] > 0
    assert r["outcome"] == "bounded" and r["inverted_at_end"] == 0, r


# ---- refusals before the first step (tissue.fem.regime) ------------------------------------------

@pytest.mark.parametrize("young, poisson", [(1e2, 0.0), (1e3, 0.45)])
def test_polar_at_the_soft_end_is_refused_naming_the_fields(backend, young, poisson):
    """ρgL/E = 9.8 and 0.98 > 0.5: the matrix's "polar" cells there ended with elements inverted
    (the linear co-rotational energy has inverted minima under a load of the order of E)."""
    r = outcome(dict(case="material", young=young, poisson=poisson, dt=0.04, rotation="polar"))
    assert r["outcome"] == "refused", r
    for field in ("rotation", "young", "density", "gravity", "rotation='invertible'"):
        assert field in r["message"], (field, r["message"])


@pytest.mark.parametrize("young, poisson", [(1e4, 0.49), (1e3, 0.45)])
def test_large_nearly_incompressible_soft_is_refused_naming_the_fields(backend, young, poisson):
    """(λ/μ) ρgL/E = 4.8 and 8.8 > 2: the matrix's "large" cells there gained energy (or ended
    inverted at dt ≥ 0.1 s). What to use instead depends on the self-weight strain (0.098: "polar";
    0.98: "invertible", since "polar" is refused there too)."""
    r = outcome(dict(case="material", young=young, poisson=poisson, dt=0.04, rotation="large"))
    assert r["outcome"] == "refused", r
    instead = "polar" if young == 1e4 else "invertible"
    for field in ("rotation", "poisson", "young", f"rotation='{instead}'"):
        assert field in r["message"], (field, r["message"])


def test_regime_criteria_against_hand_computed_numbers():
    """s = ρ|g|L/E and (λ/μ) s by hand for the 0.1 m beam, at both sides of each threshold."""
    from tissue.fem import Material
    from tissue.fem.regime import check_regime, self_weight_strain

    points = stability._mesh().points
    g = (0.0, 0.0, -9.81)
    assert self_weight_strain(Material(1e3, 0.3, 1000.0), g, 0.1) == pytest.approx(0.981, rel=1e-12)
    check_regime("polar", Material(1.97e3, 0.45, 1000.0), g, points)           # s = 0.498
    with pytest.raises(TissueError, match="'polar'"):
        check_regime("polar", Material(1.95e3, 0.0, 1000.0), g, points)       # s = 0.503
    check_regime("polar", Material(1e2, 0.3, 1000.0), (0.0, 0.0, 0.0), points)  # no gravity, no load
    check_regime("large", Material(1e4, 0.45, 1000.0), g, points)              # 9 × 0.0981 = 0.88
    with pytest.raises(TissueError, match="'large'"):
        check_regime("large", Material(1e4, 0.48, 1000.0), g, points)         # 24 × 0.0981 = 2.35 ...
    check_regime("large", Material(1e4, 0.475, 1000.0), g, points)            # ... 19 × 0.0981 = 1.86
    for rotation in ("invertible", "linear"):
        check_regime(rotation, Material(1e2, 0.499, 1000.0), g, points)


def test_a_material_changed_on_a_built_solver_is_checked_before_its_next_step(backend):
    from tissue.fem import Material

    solver = stability.solver_for(dict(dt=0.04, rotation="polar"), stability._mesh(), Material(1e4, 0.45, 1000.0))
    solver.model.set_material(Material(1e3, 0.45, 1000.0))
    x = solver.positions()
    with pytest.raises(TissueError, match="rotation: 'polar' is refused"):
        solver.step()
    assert np.array_equal(solver.positions(), x)
    solver.model.set_material(Material(1e4, 0.45, 1000.0))
    solver.step()
    with pytest.raises(TissueError, match="gravity"):
        solver.set_parameters(gravity=(0.0, 0.0, -98.1))
    assert solver.gravity == (0.0, 0.0, -9.81)      # the refused change left the solver as it was


def test_impact_onto_the_floor_is_refused_naming_dt_and_bounded_at_the_dt_it_names(backend):
    """The 10 m/s impact onto the floor at dt 0.04 s (0.4 m a step, 20 times the beam's 2 cm):
    "polar" gained 0.23 energy scales, "invertible" 1.8, "large" ended inverted; refused now. At
    the dt the message names (2 ms) "polar" stays bounded with no element inverted."""
    cell = dict(case="impact", mode="uniform", friction=0.5, rotation="polar")
    r = outcome(dict(cell, dt=0.04, steps=250))
    assert r["outcome"] == "refused" and r["message"].startswith("dt, velocities:"), r
    dt = float(r["message"].split("Use dt ≤ ")[1].split(" s")[0])
    assert dt == pytest.approx(stability.WIDTH / 10.0)
    r = outcome(dict(cell, dt=dt, steps=100))
    assert r["outcome"] == "bounded" and r["inverted_at_end"] == 0 and r["contacts_max"] > 0, r


def test_every_scene_default_passes_the_regime_check():
    """No refusal of what a user runs: each scene's bodies as the scene builds them."""
    import scenes
    from tissue.fem import Material
    from tissue.fem.regime import check_regime
    from tissue.body import build_mesh

    for name in scenes.names():
        scene = scenes.load(name)()
        for body_name, body in scene.bodies().items():
            check_regime(body.rotation, Material(body.young, body.poisson, body.density), scene.gravity,
                         build_mesh(body, body_name).points)


def test_a_scene_made_too_soft_is_refused_when_built(backend):
    """The same check on the scenes' path: the liver at 300 Pa (ρ|g|L/E = 1.7) is refused when
    its Simulation is built, the message naming the body and the field to set."""
    import scenes
    from tissue.simulation import Simulation

    scene = scenes.load("liver")().with_overrides(["liver.young=300"])
    with pytest.raises(TissueError, match=r"liver: rotation: 'polar' is refused .* rotation='invertible'"):
        Simulation(scene, arch="cpu", precision="f64")


@pytest.mark.slow   # compiles the "invertible" step (INVERTIBLE above)
@pytest.mark.parametrize("young, poisson, dt", [(1e2, 0.49, 0.01), (1e3, 0.49, 0.04), (1e2, 0.3, 0.1)])
def test_soft_end_recovers_from_inversion_with_the_compression_limit(backend, young, poisson, dt):
    """The soft end (ρgL/E = 9.8 and 0.98): "polar" is refused there (its hanging beam ended with
    elements inverted: the linear co-rotational energy's minimum has them), and "invertible", the
    rotation its message names, ends with none and its energy bounded. The last cell ended with 11
    elements inverted under the quadratic compression limit this barrier replaced (its clamp's
    corner elements held at det F ≈ 0.005)."""
    cell = dict(case="material", young=young, poisson=poisson, dt=dt)
    assert "rotation='invertible'" in outcome(dict(cell, rotation="polar"))["message"]
    r = outcome(dict(cell, rotation="invertible"))
    assert r["outcome"] == "bounded" and r["inverted_at_end"] == 0, r


@pytest.mark.slow   # compiles the "invertible" step
@pytest.mark.parametrize("poisson", [0.0, 0.3])
def test_hanging_soft_cantilever_keeps_every_element_uninverted(backend, poisson):
    """ρgL/E = 9.8, dt 10 ms (a step short enough that its linearisation holds): no step ends with
    an element inverted (signed volumes in numpy). With the barrier's restoring stress capped at
    BARRIER_END 0.3 (−5.1 κ c) the clamp's elements, one free node each, rested at the cap and
    flipped with the swing: 29 and 27 of the 100 steps ended with elements inverted."""
    r = outcome(dict(case="material", young=1e2, poisson=poisson, dt=0.01, rotation="invertible"))
    assert r["outcome"] == "bounded" and r["inverted_steps"] == 0, r


def test_a_cell_does_not_start_from_the_last_cells_solution(backend):
    """The cells warm-start CG as the scenes do, on solvers kept across cells: a cell run after
    another gives what it gives run first, on a new solver, bit for bit (its first step starts
    from zero, not from the other cell's last solution)."""
    first = dict(case="material", young=1e5, poisson=0.3, dt=0.01, rotation="polar")
    stability._solvers.clear()
    alone = stability.simulate(first)
    stability.simulate(dict(case="material", young=1e4, poisson=0.45, dt=0.04, rotation="polar"))
    after = stability.simulate(first)
    assert stability.CG["warm_start"]
    for key in ("tip_displacement", "energy_net", "cg_residual", "cg_iterations_median", "cg_iterations_max"):
        assert after[key] == alone[key], key


@pytest.mark.parametrize("rotation, advice", [("polar", "rotation 'invertible' adds one"),
                                               pytest.param("invertible", "'invertible' barrier did not hold",
                                                            marks=pytest.mark.slow)])
def test_the_inversion_warning_fits_the_rotation(backend, rotation, advice):
    """The solver's warning about inverted elements (the inverted node: 6 at the start) says what
    to try for a rotation without a barrier, and what failed for the one with it."""
    from tissue.fem import Material

    cell = dict(case="inverted", mode="node", dt=0.04, rotation=rotation)
    mesh = stability._mesh()
    x, v, fixed = stability.initial_state(cell, mesh)
    solver = stability.solver_for(cell, mesh, Material(1e4, 0.45, 1000.0))
    solver.set_fixed(fixed)
    solver.set_state(x, v)
    with pytest.warns(UserWarning, match="6 elements are inverted") as caught:
        solver.step()
    assert any(advice in str(w.message) for w in caught), [str(w.message) for w in caught]


def test_hard_jerk_of_the_clamped_end_stays_bounded(backend):
    r = outcome(dict(case="jerk", mode="half-length", dt=0.04, steps=100, rotation="polar"))
    assert r["outcome"] == "bounded", r


# ---- with contact (rigid obstacles, Coulomb friction, compliance warping) ------------------------

@pytest.mark.parametrize("case, mode", [("jerk", "half-length"), ("rest", "clamped")])
@pytest.mark.parametrize("rotation", [LARGE, "polar"])
def test_cantilever_on_the_floor_stays_bounded(backend, case, mode, rotation):
    """The clamped end jerked by half the length, or the beam sagging from rest, onto the floor.
    With "large" the compliance warped by its edge frames added energy (the resting beam: 28.8
    energy scales, 37 elements inverted; the jerk: elements left inverted): the contact stage
    warps with polar rotations now, and the energy budget holds each step to its start."""
    r = outcome(dict(case=case, mode=mode, friction=0.5, dt=0.04, steps=100, rotation=rotation))
    assert r["outcome"] == "bounded" and r["contacts_max"] > 0, r


@pytest.mark.parametrize("mode, mu, slides", [("floor", 0.0, True), ("floor", 10.0, False),
                                              ("slope", 0.1, True), ("slope", 1.0, False)])
def test_block_slides_or_sticks_and_stays_bounded(backend, mode, mu, slides):
    """Launched along the floor at 0.3 m/s, or released on the 25° slope (tan 25° = 0.47): in 2 s
    it slides metres where μ allows, and stops within a few millimetres where it does not."""
    r = outcome(dict(case="friction", mode=mode, friction=mu, dt=0.04, steps=50, rotation="polar"))
    assert r["outcome"] == "bounded" and r["contacts_max"] > 0, r
    assert r["travel"] > 0.5 if slides else r["travel"] < 0.01, r


def test_slab_pressed_by_a_plate_has_over_2000_rows(backend):
    """The first steps of the press: the floor's 361 bottom vertices and the plate's 361 top ones
    (found by the alarm distance at the step's start: the free motion drops the slab 15.7 mm),
    and 72 side vertices the free motion takes below the floor: 2,382 rows."""
    r = outcome(dict(case="press", mode="plate", friction=0.5, dt=0.04, steps=3, rotation="polar"))
    assert r["rows_max"] == 2382, r
    assert r["outcome"] == "bounded", r


def test_gravity_from_rest_loses_energy(backend):
    r = outcome(dict(case="material", young=1e5, poisson=0.3, dt=0.04, rotation="polar"))
    assert r["outcome"] == "bounded" and r["energy_net"] < 0, r


@pytest.mark.parametrize("state", ["nan positions", "collapsed to a point"])
def test_no_silent_nan(backend, state):
    mesh = stability._mesh()
    from tissue.fem import Material

    solver = stability.solver_for(dict(dt=0.04), mesh, Material(1e4, 0.45, 1000.0))
    x, _, fixed = stability.initial_state(dict(case="material"), mesh)
    solver.set_fixed(fixed)
    if state == "nan positions":
        x[5] = np.nan
    else:
        x[:] = x[0]
    solver.set_state(x, np.zeros_like(x))
    try:
        solver.step()
    except TissueError as e:
        assert "diverged" in str(e)
        return
    assert np.isfinite(solver.positions()).all() and np.isfinite(solver.velocities()).all()


# ---- the nonlinear reference the accuracy bench relies on (numpy only) -------------------------

@pytest.fixture(scope="module")
def body():
    from tissue.fem import Material
    from tissue.mesh import beam

    mesh = beam(1.0, 0.1, 0.1, 10, 1)
    return Body(mesh, Material(1e6, 0.3, 1000.0), np.flatnonzero(mesh.points[:, 0] < 1e-9))


def deformed(mesh, seed=0):
    rng = np.random.default_rng(seed)
    c, s = np.cos(0.7), np.sin(0.7)
    return (mesh.points + 0.01 * rng.standard_normal(mesh.points.shape)) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


@pytest.mark.parametrize("rotation", ["large", "polar", "linear"])
def test_reference_corotational_forces_match_the_scipy_reference(body, rotation):
    from tissue.solver.reference import linearise

    x = deformed(body.mesh)
    expected = linearise(body.mesh, body.material, x, np.zeros_like(x), 1.0, rotation=rotation).forces
    assert np.allclose(internal_forces(body, rotation, x).ravel(), expected, rtol=0, atol=1e-12 * abs(expected).max())


@pytest.mark.parametrize("model", ["stvk", "large", "polar"])
def test_reference_tangents_match_differenced_forces(body, model):
    x = deformed(body.mesh, 1)
    d = 1e-7 * np.random.default_rng(2).standard_normal(x.shape)
    differenced = -(internal_forces(body, model, x + d) - internal_forces(body, model, x - d)).ravel() / 2
    assert np.linalg.norm(tangent(body, model, x) @ d.ravel() - differenced) < 1e-6 * np.linalg.norm(differenced)


def test_stvk_has_no_force_under_rigid_motion(body):
    c, s = np.cos(1.0), np.sin(1.0)
    x = body.mesh.points @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T + 3.0
    forces = internal_forces(body, "stvk", x)
    assert abs(forces).max() < 1e-9 * body.material.young * body.mesh.volumes.sum() ** (2 / 3)


def test_obstacle_work_of_a_rising_floor(backend):
    """The free block resting on a floor that rises at u = 1 cm/s for T = 2 s: the floor lifts it
    by u T, so its work is m g u T + ½ m u² (the block's potential and kinetic energy gained),
    less what the block's own settling and damping take (its sag ρ g H / E = 2 % of its 2 cm
    height: under 1 % of the lift)."""
    from tissue.contact import Contact
    from tissue.contact.layer import obstacle_work
    from tissue.contact.obstacles import Plane, RigidObstacle
    from tissue.contact.pipeline import ContactStage
    from tissue.fem import Material

    u, dt, steps = 0.01, 0.04, 50
    cell = dict(case="friction", mode="floor", dt=dt, rotation="polar")
    mesh = stability._mesh("block")
    solver = stability.solver_for(cell, mesh, Material(1e4, 0.45, 1000.0))
    solver.set_fixed([])
    solver.set_state(mesh.points, np.zeros_like(mesh.points))
    floor = RigidObstacle(Plane((0.0, 0.0, 0.0)), name="floor", motion=lambda t: np.array([0.0, 0.0, u * t]))
    stage = ContactStage([solver], [floor], Contact(friction=0.5, distance=stability.CONTACT_DISTANCE))
    work = 0.0
    for _ in range(steps):
        solver.step()
        work += obstacle_work(stage.step(), 0)
    mass = solver.model.mass.sum()
    lift = u * dt * steps
    rise = (solver.model.mass @ (solver.positions() - mesh.points))[2] / mass
    assert rise == pytest.approx(lift, rel=0.05)
    assert work == pytest.approx(mass * 9.81 * lift + 0.5 * mass * u * u, rel=0.02)


def _square_unless_three(cell):
    if cell["i"] == 3:
        raise ValueError("cell three fails")
    return {**cell, "square": cell["i"] ** 2}


def test_sweep_keeps_the_cells_order_records_a_crash_and_shows_progress(capsys):
    """bench.cluster.run_cells: results in the order of the cells whatever order they finish in,
    a cell that raises is that cell's error (not the sweep's end), and progress is printed."""
    from dask.distributed import Client, LocalCluster

    from bench.cluster import run_cells

    cells = [{"i": i} for i in range(30)]
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        out = run_cells(client, _square_unless_three, cells, "sweep")
    assert [r["i"] for r in out] == list(range(30))
    assert out[3]["error"] == "ValueError: cell three fails"
    assert all(r["square"] == r["i"] ** 2 for r in out if r["i"] != 3)
    printed = capsys.readouterr().out
    assert "sweep: 15 of 30 tasks done" in printed and "sweep: 30 tasks in" in printed
