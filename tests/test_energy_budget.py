"""The energy budget (tissue.solver.energy_budget): every step of a "large" twist that gains
energy without it ends within its start's energy with it; a body whose steps lose energy is not
touched (bit for bit); and a projection removes exactly the excess, from the kinetic energy when
it holds it, else back along the step. Energies are measured here in numpy (tissue.fem.energy's
reference), not by the budget's kernel."""

import numpy as np
import pytest

from bench import stability
from tissue.fem import Material
from tissue.fem.energy import elastic_energy
from tissue.solver.step_control import EnergyControl

MATERIAL = Material(1e4, 0.45, 1000.0)


def start(cell):
    mesh = stability._mesh()
    x0, v0, fixed = stability.initial_state(cell, mesh)
    solver = stability.solver_for(cell, mesh, MATERIAL)
    solver.set_fixed(fixed)
    solver.set_state(x0, v0)
    return solver


def energy(solver) -> float:
    """Kinetic + the polar co-rotational energy + gravity's potential, in numpy."""
    x, v, m = solver.positions(), solver.velocities(), solver.model.mass
    return 0.5 * m @ (v * v).sum(1) + elastic_energy(solver.model, x, "polar") - m @ (x @ np.asarray(stability.GRAVITY))


def energies(solver, stepper, steps):
    out = [energy(solver)]
    for _ in range(steps):
        stepper.step()
        out.append(energy(solver))
    return np.array(out)


@pytest.mark.parametrize("budget", [False, True])
def test_budget_holds_where_large_steps_gain_energy(backend, budget):
    """The abrupt twist with "large" (its forces are no energy's gradient), every step taken once
    (no energy check): without the budget steps gain up to 3 % of the start energy; with it none
    gains more than rounding."""
    solver = start(dict(case="twist", mode="abrupt", dt=0.04, rotation="large"))
    control = EnergyControl(solver, tolerance=np.inf, max_halvings=0, budget=budget)
    E = energies(solver, control, 40)
    gain = np.diff(E).max() / E[0]
    print(f"budget {budget}: largest gain of a step {gain:.2e} of the start energy")
    if budget:
        assert gain <= 1e-9
        assert sum(solver.stats.history["budget_projections"]) > 0
        assert sum(solver.stats.history["budget_unresolved"]) == 0
    else:
        assert gain > 1e-2


def test_no_projection_where_every_step_loses_energy(backend):
    """The "polar" beam swinging down from rest (its energy only falls): with the budget the
    trajectory is the one without it, bit for bit, and nothing is projected."""
    cell = dict(case="material", young=1e5, poisson=0.3, dt=0.01, rotation="polar")
    runs = []
    for budget in (False, True):
        solver = start(cell)
        control = EnergyControl(solver, budget=budget)
        E = energies(solver, control, 30)
        runs.append((solver.positions(), solver.velocities()))
    assert np.all(np.diff(E) <= 0)
    assert sum(solver.stats.history["budget_projections"]) == 0
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])


def test_projection_scales_the_velocities_by_the_excess(backend):
    """A step of the swinging beam, its budget set below its end by half its kinetic energy K:
    the velocities are scaled by √(1 − excess/K), the positions kept, and the energy is then the
    budget (conserved to it, not below)."""
    solver = start(dict(case="material", young=1e5, poisson=0.3, dt=0.01, rotation="polar"))
    control = EnergyControl(solver, budget=True)
    for _ in range(5):
        control.step()
    control.budget.open(control.energy())
    solver.step()
    x1, v1 = solver.positions(), solver.velocities()
    excess = 0.5 * (0.5 * solver.model.mass @ (v1 * v1).sum(1))
    control.budget.allowed = energy(solver) - excess
    control.budget.close()
    assert solver.stats.counters["budget_projections"] == 1
    assert solver.stats.counters["budget_removed"] == pytest.approx(excess, rel=1e-9)
    assert np.array_equal(solver.positions(), x1)
    np.testing.assert_allclose(solver.velocities(), np.sqrt(0.5) * v1, rtol=1e-14, atol=0)
    assert energy(solver) == pytest.approx(control.budget.allowed, rel=1e-12)


def test_projection_goes_back_along_the_step_where_kinetic_energy_is_short(backend):
    """The smooth twist with "large" gains more elastic energy in a step than its kinetic energy
    holds: the state goes back along the step, (x₀ + s (x − x₀), s v) with 0 ≤ s < 1, and ends
    within its start's energy."""
    solver = start(dict(case="twist", mode="smooth", dt=0.04, rotation="large"))
    control = EnergyControl(solver, tolerance=np.inf, max_halvings=0, budget=True)
    for _ in range(40):     # to the first step whose gain its kinetic energy cannot take
        before = energy(solver)
        x0 = solver.positions()
        control.budget.open(control.energy())
        solver.step()
        x1, v1 = solver.positions(), solver.velocities()
        if energy(solver) - before > 0.5 * solver.model.mass @ (v1 * v1).sum(1):
            break
        control.budget.close()
    else:
        pytest.fail("no step of the twist gained more than its kinetic energy")
    control.budget.close()
    x, v = solver.positions(), solver.velocities()
    assert solver.stats.counters["budget_projections"] == 1
    assert solver.stats.counters["budget_unresolved"] == 0
    assert energy(solver) <= before + 1e-12 * abs(before)
    moved = np.abs(x1 - x0).max()
    s = np.abs(x - x0).max() / moved
    assert 0.0 <= s < 1.0
    np.testing.assert_allclose(x, x0 + s * (x1 - x0), rtol=0, atol=1e-12 * moved)
    assert np.all(np.linalg.norm(v, axis=1) <= s * np.linalg.norm(v1, axis=1) * (1 + 1e-12))


@pytest.mark.parametrize("counted", [True, False])
def test_a_rising_floor_does_work_the_budget_lets_in(backend, counted):
    """The free block on a floor rising at 1 cm/s for 2 s: the floor's work (the block's potential
    and kinetic energy gained) enters each step's budget (as the contact layer adds it), so the
    block is lifted by the floor's travel, nothing held back. Left out of the budget (the
    control), the lift is projected away at every step."""
    from tissue.contact import Contact
    from tissue.contact.layer import obstacle_work
    from tissue.contact.obstacles import Plane, RigidObstacle
    from tissue.contact.pipeline import ContactStage

    u, dt, steps = 0.01, 0.04, 50
    cell = dict(case="friction", mode="floor", dt=dt, rotation="polar")
    mesh = stability._mesh("block")
    solver = stability.solver_for(cell, mesh, MATERIAL)
    solver.set_fixed([])
    solver.set_state(mesh.points, np.zeros_like(mesh.points))
    floor = RigidObstacle(Plane((0.0, 0.0, 0.0)), name="floor", motion=lambda t: np.array([0.0, 0.0, u * t]))
    stage = ContactStage([solver], [floor], Contact(friction=0.5, distance=stability.CONTACT_DISTANCE))
    control = EnergyControl(solver, budget=True)
    for _ in range(steps):
        control.step()
        work = obstacle_work(stage.step(), 0)
        control.budget.add_work(work if counted else 0.0)
        control.budget.close()
    mass = solver.model.mass
    rise = (mass @ (solver.positions() - mesh.points))[2] / mass.sum()
    if counted:
        assert rise == pytest.approx(u * dt * steps, rel=0.05)
        assert sum(solver.stats.history["budget_unresolved"]) == 0
    else:
        assert rise < 0.1 * u * dt * steps


def test_the_contact_layer_closes_the_budget_after_its_correction(backend):
    """A scene with contact (`incline`: the block on the slope from its first step): each step's
    budget is closed twice, after the free motion and after the contact correction; where nothing
    is projected the run is the one without the budget, bit for bit."""
    import scenes
    from tissue.simulation import Simulation

    runs = {}
    for budget in (False, True):
        sim = Simulation(scenes.load("incline")().with_overrides([f"solver.energy_budget={str(budget).lower()}"]))
        for _ in range(5):
            sim.step()
        runs[budget] = (sim.bodies["block"].positions(), sim.bodies["block"].solver.stats.history)
    history = runs[True][1]
    assert len(history["budget_projections"]) == 2 * 5
    assert "budget_projections" not in runs[False][1]
    assert sum(history["budget_projections"]) == 0
    assert np.array_equal(runs[True][0], runs[False][0])
