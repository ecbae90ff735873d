"""Energy-checked steps (tissue.solver.step_control) and the elastic energy they read
(tissue.fem.energy): the energy against the numpy reference of bench/nonlinear_reference.py, the
accounting of gravity and applied forces against free fall in closed form, a rejected step against
two half steps taken by hand, and the hanging soft beam that one linearisation per step drives up
in energy and the check keeps bounded; the check's energy kernel against that numpy energy; and a
swinging step's gain against the balance of a step linearised once and against steps that do not
leave out the rotations' derivative."""

import numpy as np
import pytest
import scipy.linalg

from bench import stability
from bench.free_motion_energy import Reference
from bench.nonlinear_reference import Body, strain_energy, tangent
from tissue.errors import TissueError
from tissue.fem import CorotationalFEM, Material
from tissue.fem.energy import deformation_gradients, elastic_energy, element_energies
from tissue.fem.model import BodyModel
from tissue.solver import CGSettings, ImplicitEuler
from tissue.solver.step_control import EnergyControl

MATERIAL = Material(1e4, 0.45, 1000.0)


@pytest.mark.parametrize("rotation", ["polar", "invertible", "linear"])
@pytest.mark.parametrize("amplitude", [1e-3, 3e-2])
def test_elastic_energy_matches_the_reference(rotation, amplitude):
    """Turned by 1 rad and perturbed, some elements inverted at the larger amplitude: the
    strain-based energy against the reference's ½ uᵀ Kₑ u (plus the compression limit's)."""
    mesh = stability._mesh()
    rng = np.random.default_rng(3)
    c, s = np.cos(1.0), np.sin(1.0)
    x = (mesh.points + amplitude * rng.standard_normal(mesh.points.shape)) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    expected = strain_energy(Body(mesh, MATERIAL, np.zeros(0, dtype=np.int64)), rotation, x)
    assert elastic_energy(BodyModel(mesh, MATERIAL), x, rotation) == pytest.approx(expected, rel=1e-12)


def test_bad_settings_are_refused(backend):
    solver = stability.solver_for(dict(dt=0.04, rotation="polar"), stability._mesh(), MATERIAL)
    with pytest.raises(TissueError, match="tolerance"):
        EnergyControl(solver, tolerance=-1.0)
    with pytest.raises(TissueError, match="max_halvings"):
        EnergyControl(solver, max_halvings=-1)


@pytest.mark.parametrize("load", ["gravity", "applied forces"])
def test_free_fall_energy_in_closed_form(backend, load):
    """A free body from rest, no elastic strain: implicit Euler with mass damping α gives
    v₁ = h a / (1 + h α) and x₁ = x₀ + h v₁, so the energy less the load's work changes by
    m v₁ (v₁/2 − h a) < 0. The check accepts the step and measures that change (a wrong sign on
    the load's potential would read a gain and reject it)."""
    dt, a = 0.04, 9.81
    mesh = stability._mesh()
    solver = stability.solver_for(dict(dt=dt, rotation="polar", cg=dict(tolerance=1e-13)), mesh, MATERIAL)
    solver.set_fixed([])
    mass = solver.model.mass
    if load == "gravity":
        forces = None
    else:
        solver.set_parameters(gravity=(0.0, 0.0, 0.0))
        forces = np.outer(mass, [0.0, 0.0, -a])
    try:
        solver.set_external_forces(forces)
        solver.set_state(mesh.points, np.zeros_like(mesh.points))
        control = EnergyControl(solver, tolerance=0.0)
        before = sum(control.energy())
        control.step()
        after = sum(control.energy())
    finally:
        solver.set_parameters(gravity=stability.GRAVITY)
        solver.set_external_forces(None)
    v1 = dt * a / (1.0 + dt * 0.1)
    expected = mass.sum() * v1 * (v1 / 2 - dt * a)
    assert np.allclose(solver.velocities(), [0.0, 0.0, -v1], rtol=0, atol=1e-9 * v1)
    assert after - before == pytest.approx(expected, rel=1e-6)
    assert solver.stats.counters["energy_rejections"] == 0


def test_a_rejected_step_is_two_half_steps(backend):
    """The hanging soft beam's first step at dt 0.5 s gains energy: with one halving allowed the
    check's result is the state two steps of dt/2 reach from the same start (CG started cold: a
    warm start would begin each solve from the last one's, which differs between the two)."""
    mesh = stability._mesh()
    cell = dict(case="material", young=1e4, poisson=0.45, dt=0.5, rotation="polar", cg=dict(warm_start=False))
    x0, v0, fixed = stability.initial_state(cell, mesh)
    solver = stability.solver_for(cell, mesh, MATERIAL)
    solver.set_fixed(fixed)
    solver.set_state(x0, v0)
    EnergyControl(solver, tolerance=0.0, max_halvings=1).step()
    assert solver.stats.counters["energy_rejections"] == 1 and solver.dt == 0.5
    controlled = solver.positions(), solver.velocities()
    solver.set_state(x0, v0)
    solver.set_parameters(dt=0.25)
    try:
        solver.step()
        solver.step()
    finally:
        solver.set_parameters(dt=0.5)
    assert np.allclose(controlled[0], solver.positions(), rtol=0, atol=1e-12)
    assert np.allclose(controlled[1], solver.velocities(), rtol=0, atol=1e-12)


def test_start_energy_reused_only_where_the_last_step_ended(backend):
    """A step starts where the last one ended: the check reuses that end's elastic energy (one
    evaluation a step). A state set in between, or a material changed, is evaluated afresh, to
    the value a new check finds to round-off: the step's launch and the evaluation's own are
    compiled apart, and LLVM contracts the same arithmetic differently in them. An element's energy
    comes from its strain ε = RᵀF − I, a difference that loses |F|/|ε| of the precision, so the two
    agree to one rounding of each element's ε: Σ 2 eᵢ · eps/|εᵢ| (the strains from scipy's polar)."""
    mesh = stability._mesh()
    cell = dict(case="material", young=1e6, poisson=0.3, dt=0.01, rotation="polar")
    x0, v0, fixed = stability.initial_state(cell, mesh)
    solver = stability.solver_for(cell, mesh, Material(1e6, 0.3, 1000.0))
    solver.set_fixed(fixed)
    solver.set_state(x0, v0)
    control = EnergyControl(solver)

    def evaluations(change=None):
        if change is not None:
            change()
        before = control.evaluations
        control.step()
        assert solver.stats.counters["energy_rejections"] == 0
        return control.evaluations - before

    assert [evaluations(), evaluations(), evaluations()] == [2, 1, 1]
    assert evaluations(lambda: solver.set_state(solver.positions(), 1.01 * solver.velocities())) == 2
    assert evaluations(lambda: solver.fem.model.set_material(Material(2e6, 0.3, 1000.0))) == 2
    x = solver.positions()
    F = deformation_gradients(solver.fem.model, x)
    strains = np.array([np.linalg.norm(scipy.linalg.polar(f)[0].T @ f - np.eye(3)) for f in F])
    round_off = 2 * np.finfo(float).eps * np.sum(element_energies(solver.fem.model, x, "polar") / strains)
    assert control.energy() == pytest.approx(EnergyControl(solver).energy(), rel=0.0, abs=round_off)


@pytest.mark.parametrize("execution", ["serial", "parallel"])
@pytest.mark.parametrize("rotation", ["large", "polar", "invertible", "linear"])
def test_energy_kernel_matches_numpy(backend, rotation, execution):
    """The check's kernel against the numpy energy (tissue.fem.energy, itself checked against the
    reference above) on a turned, perturbed beam with inverted elements: kinetic + elastic, the
    potential of gravity and applied forces, and the sum of its terms' magnitudes (the energy
    budget's rounding scale), to 1e-12; where the solver runs serially, also the evaluation at a
    step's start in the step's launch."""
    from tissue.solver import ImplicitEuler

    mesh = stability._mesh()
    rng = np.random.default_rng(7)
    c, s = np.cos(1.0), np.sin(1.0)
    x = (mesh.points + 3e-2 * rng.standard_normal(mesh.points.shape)) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    v = rng.standard_normal(x.shape)
    forces = rng.standard_normal(x.shape)
    gravity = np.array([0.5, -1.0, -9.81])
    solver = ImplicitEuler(CorotationalFEM(mesh, MATERIAL, rotation=rotation), 0.01, gravity=tuple(gravity),
                           execution=execution)
    model = solver.model
    assert (np.linalg.det(deformation_gradients(model, x)) < 0).sum() >= 5
    solver.set_state(x, v)
    solver.set_external_forces(forces)
    control = EnergyControl(solver)
    inner, potential = control.energy()
    elastic = elastic_energy(model, x, rotation)
    assert inner == pytest.approx(elastic + 0.5 * model.mass @ (v * v).sum(1), rel=1e-12)
    assert potential == pytest.approx(-model.mass @ (x @ gravity) - (forces * x).sum(), rel=1e-12)
    terms = inner + np.abs(((np.outer(model.mass, gravity) + forces) * x).sum(1)).sum()     # Σ|terms|
    assert control.terms == pytest.approx(terms, rel=1e-12)
    if execution == "serial":       # the evaluation at a step's start in its launch, from its rotations
        checked = EnergyControl(solver)
        start, _ = checked._checked_step(None)
        assert start == pytest.approx((inner, potential), rel=1e-12)
        assert checked._start_terms == pytest.approx(terms, rel=1e-12)
        solver.set_state(x, v)
    solver.set_state(velocities=np.zeros_like(v))
    assert EnergyControl(solver).energy()[0] == pytest.approx(elastic, rel=1e-12)


@pytest.mark.parametrize("execution", ["serial", "parallel"])
@pytest.mark.parametrize("rotation", ["large", "polar", "invertible"])
def test_energy_launch_takes_the_stiffness_product(backend, rotation, execution):
    """`energy(times=p)` (the energy budget's correction term) on the turned, perturbed beam after
    a step: the same energy as without p, and Σ R Kₑ Rᵀ p at the step's rotations as the FEM's own
    standalone product gives it (its compression limit's tangent too, "invertible"), to 1e-12."""
    from tissue.solver import ImplicitEuler

    mesh = stability._mesh()
    rng = np.random.default_rng(7)
    c, s = np.cos(1.0), np.sin(1.0)
    x = (mesh.points + 3e-2 * rng.standard_normal(mesh.points.shape)) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    solver = ImplicitEuler(CorotationalFEM(mesh, MATERIAL, rotation=rotation), 0.01, execution=execution)
    solver.set_state(x, rng.standard_normal(x.shape))
    solver.step()
    p = rng.standard_normal(x.shape)
    control = EnergyControl(solver)
    plain = control.energy()
    assert control.energy(times=p) == plain
    expected = -solver.fem.stiffness_product_numpy(p)
    np.testing.assert_allclose(control.stiffness_product(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("young, dt", [(1e4, 0.5), (2e3, 0.1)])
def test_soft_beam_at_large_steps_gains_energy_unless_checked(backend, young, dt):
    """ρgL/E = 0.098 and 0.49 (the softest "polar" accepts: tissue.fem.regime): the beam swings
    down by order one of its length per step. Each step solved to ‖r‖ ≤ 1e-3 ‖b‖, unchecked it
    gains more than the 1 % allowance (13 and 2.2 energy scales when measured); checked it stays
    bounded."""
    cell = dict(case="material", young=young, poisson=0.3, dt=dt, rotation="polar")
    unchecked = stability.simulate(dict(cell, step_control="none"))
    assert unchecked["outcome"] == "energy" and unchecked["cg_steps_at_cap"] == 0, unchecked
    checked = stability.simulate(cell)
    assert checked["outcome"] == "bounded" and checked["energy_rejections"] > 0, checked


@pytest.mark.parametrize("rotation", ["large", "polar", "invertible", "linear"])
def test_checked_serial_step_matches_separate_evaluations(backend, rotation):
    """The serial step with both evaluations in its launch against the step and the evaluations
    launched apart: the same rejections, the energies to 1e-12 (of the largest; the start's from the step's
    rotations, not an eigensolve) and the states to 1e-12 (the same arithmetic; Taichi's fast math
    lets LLVM contract it differently in the larger kernel: bit for bit with fast_math=False). The
    velocities are scaled between steps, as a contact correction moves the state, so every start is
    evaluated afresh."""
    from tissue.solver import CGSettings, ImplicitEuler

    mesh = stability._mesh()
    material = Material(2e3, 0.3, 1000.0)
    cell = dict(case="material", young=material.young, poisson=material.poisson, dt=0.1, rotation=rotation)
    x0, v0, fixed = stability.initial_state(cell, mesh)
    runs = []
    for fused in (True, False):
        solver = ImplicitEuler(CorotationalFEM(mesh, material, rotation=rotation), cell["dt"],
                               gravity=stability.GRAVITY, rayleigh_mass=0.1, rayleigh_stiffness=0.1, execution="serial",
                               cg=CGSettings(max_iterations=100, tolerance=1e-6, preconditioner="jacobi"))
        solver.set_fixed(fixed)
        solver.set_state(x0, v0)
        control = EnergyControl(solver, fused=fused)
        energies, checked_step = [], control._checked_step

        def logged(start, checked_step=checked_step, energies=energies, control=control):
            start, end = checked_step(start)
            energies.append((*start, *end, control.terms))     # and Σ|terms| at the end
            return start, end

        control._checked_step = logged
        states = []
        for _ in range(6):
            control.step()
            states.append(np.concatenate([solver.positions(), solver.velocities()]))
            solver.set_state(velocities=0.9 * solver.velocities())
        runs.append((np.array(states), np.array(energies), solver.stats.history["energy_rejections"]))
    (fused, fused_energies, fused_rejections), (apart, apart_energies, apart_rejections) = runs
    assert fused_rejections == apart_rejections
    assert sum(apart_rejections) > 0 or rotation == "linear"     # (a linear step only loses energy)
    assert np.abs(fused - apart).max() <= 1e-12 * np.abs(apart).max()
    # to 1e-12 of the energies in play (the rest state's elastic energy is round-off)
    assert np.abs(fused_energies - apart_energies).max() <= 1e-12 * np.abs(apart_energies).max()


def test_a_swinging_step_gains_only_by_the_linearisation(backend):
    """Why a free body's step gains energy (the organs' colon: bench/free_motion_energy.py), on the
    cantilever hanging under its weight (E 1e4 Pa, ν 0.3, dt 0.02 s, Rayleigh 0.1 / 0.02, the
    colon's), whose 5th step from rest gains 1.9e-3 of the energy in play. References in numpy and
    scipy (bench.free_motion_energy.Reference): the solver's step (CG to 1e-12) changes the energy
    by exactly the balance of a step linearised once, −½ dvᵀM dv − ½ h² v₁ᵀK v₁ − h v₁ᵀB v₁ + N,
    N the co-rotational energy's departure from the step's quadratic model: N is larger than all
    the dissipation. From the same start, the same linearised step with the exact tangent (the
    rotations' derivative, which K leaves out) loses energy, as do backward Euler solved by Newton
    and two steps of dt/2: the gain is the tangent's, not CG's, the held nodes' or backward Euler's."""
    dt, damping = 0.02, dict(rayleigh_mass=0.1, rayleigh_stiffness=0.02)
    material = Material(1e4, 0.3, 1000.0)
    mesh = stability._mesh()
    x, v, fixed = stability.initial_state(dict(case="material"), mesh)
    solver = ImplicitEuler(CorotationalFEM(mesh, material, rotation="polar"), dt, gravity=stability.GRAVITY,
                           cg=CGSettings(max_iterations=500, tolerance=1e-12), fixed=fixed, **damping)
    solver.set_state(x, v)
    reference = Reference(mesh, material, fixed, stability.GRAVITY, **damping)
    for _ in range(4):
        solver.step()
    x0, v0 = solver.positions(), solver.velocities()
    solver.step()
    x1, v1 = solver.positions(), solver.velocities()
    e0 = reference.energy(x0, v0)
    gain = reference.energy(x1, v1) - e0
    scale = max(reference.inner(x0, v0), reference.inner(x1, v1))
    assert gain > 1e-3 * scale
    balance = reference.balance(x0, v0, dt)
    dissipation = -(balance["mass"] + balance["stiffness"] + balance["damping"])
    assert gain == pytest.approx(balance["N"] - dissipation, abs=1e-9 * scale)
    assert balance["scipy"] == pytest.approx(gain, abs=1e-9 * scale)
    assert balance["N"] > dissipation > 0
    exact = reference.step(x0, v0, dt, tangent(reference.nl, "polar", x0))
    assert reference.energy(*exact[:2]) < e0
    assert reference.energy(*reference.newton(x0, v0, dt)[:2]) < e0
    half = reference.step(*reference.step(x0, v0, dt / 2)[:2], dt / 2)
    assert reference.energy(*half[:2]) < e0
