"""Energy-checked steps: a step that raised the body's energy is redone as two half steps.

The implicit step linearises the co-rotational forces once (the rotation's derivative left out of
the tangent, as SOFA and the paper do). Where elements turn or strain by order one within a step
(soft material under its own weight at dt 0.1-0.5 s, a 10 m/s impact, a beam swinging down), the
linear extrapolation lands above the energy it started from, and the step gains energy although
damped implicit Euler on the same linear problem only loses it. A smaller step linearises over a
smaller motion: the error of the linearisation falls with dt², the damping's loss with dt.

`EnergyControl.step()` takes the solver's step and checks the body's total energy: kinetic +
elastic (the model's own: tissue.fem.energy) less the work of gravity and the applied nodal
forces over the step. If it rose by more than `tolerance` of the energy in play, the step is
undone and taken as two steps of dt/2, each checked the same way, down to dt / 2^max_halvings; a
step still gaining energy there is kept, and counted (`energy_unresolved` in the solver's stats).
The stats also count the step's rejections (`energy_rejections`). With `budget`, the step's end
is then held to its start's energy plus the work done on it, plus the allowance its solves' own
error earns (tissue.solver.energy_budget: the CG residuals the kept solves leave are measured here).

The energy is evaluated on the device over the solver's arrays (nothing copied to the host): per
element from its polar rotation, or its stretches where Newton–Schulz does not find the rotation
(tissue.fem.energy), summed in a fixed order. Where
the solver runs serially, one launch takes the step and both evaluations (`_checked_serial`): the
start's from the rotations the step computes (no eigensolve), the end's after it. Otherwise the
evaluation is a launch of its own (a per-element buffer, then a serial sum) before and after the
step. The evaluations keep the last two states they saw (x, v), alternately: a state equal to the
one before, bit for bit, on an unedited model (`BodyModel.edits`), reuses its elastic energy (a
step's start is where the last one ended, unless the contact stage's correction moved it); and the
state a step started from is there to undo the step. Costs: the evaluations, and the rejected
steps' work (bench/step_control.py).
"""

import numpy as np
import taichi as ti

from .. import backend, compilation
from ..errors import TissueError
from ..fem import corotational
from ..fem.energy import element_energy, element_energy_at_rotations
from ..fem.model import real_numpy
from ..launch import host_view, replayed
from .energy_budget import EnergyBudget, solve_residual
from .parameters import GX, GY, GZ
from .step_kernels import STEP, begin, end, inlines_multigrid, solve_serial

TOLERANCE = 1e-3        # of the energy in play (kinetic + elastic), the most a step may gain
MAX_HALVINGS = 6        # dt / 64 at the finest

# The evaluations' own arrays: per-element energies, the last two states evaluated (slot, node),
# their totals (slots below), and a nodal vector and its stiffness product (`energy(times=...)`:
# the energy budget's correction term, in the launch the budget's close makes anyway, so that no
# scene compiles a kernel more). Named apart from the step's arrays (its "product"): Taichi 1.7
# mixes up like-named members of two argpacks in one kernel.
ENERGY_WORK = ti.types.argpack(per_element=ti.types.ndarray(), seen_x=ti.types.ndarray(),
                               seen_v=ti.types.ndarray(), totals=ti.types.ndarray(), direction=ti.types.ndarray(),
                               stiffness_direction=ti.types.ndarray())
# The elastic energy of the last evaluation and whether it was fresh; then the (kinetic + elastic,
# potential, fresh, Σ|terms|) of an evaluation at a step's start and at its end.
ELASTIC, FRESH, AT_START, AT_END = 0, 1, 2, 6
TOTALS = 10


@ti.func
def _keep_state(k: ti.template(), w: ti.template(), previous, edited):
    """Keep the solver's state in slot 1 − previous; FRESH: whether it differs from slot
    `previous` or the model was `edited` (one thread)."""
    changed = edited
    for v in range(k.counts[0]):
        if (k.x[v] != w.seen_x[previous, v]).any() or (k.v[v] != w.seen_v[previous, v]).any():
            changed = 1
        w.seen_x[1 - previous, v] = k.x[v]
        w.seen_v[1 - previous, v] = k.v[v]
    w.totals[FRESH] = changed


@ti.func
def _close_evaluation(k: ti.template(), w: ti.template(), out):
    """The kinetic energy and the potential of gravity and the applied forces; then the evaluation's
    (kinetic + elastic, potential, fresh, Σ|terms|) into totals[out:out + 4] (one thread); Σ|terms|,
    the sum of the magnitudes of the terms summed (kinetic and elastic ones are ≥ 0), sizes the
    sums' rounding (tissue.solver.energy_budget)."""
    g = ti.Vector([k.parameters[GX], k.parameters[GY], k.parameters[GZ]])
    kinetic, potential, magnitude = 0.0, 0.0, 0.0
    for v in range(k.counts[0]):
        kinetic += 0.5 * k.mass[v] * k.v[v].norm_sqr()
        term = (k.mass[v] * g + k.external[v]).dot(k.x[v])
        potential -= term
        magnitude += ti.abs(term)
    w.totals[out] = kinetic + w.totals[ELASTIC]
    w.totals[out + 1] = potential
    w.totals[out + 2] = w.totals[FRESH]
    w.totals[out + 3] = w.totals[out] + magnitude


@ti.func
def _evaluate_serial(k: ti.template(), w: ti.template(), rotation: ti.template(), at_rotations: ti.template(),
                     previous, edited, out, tol):
    """An evaluation in one thread, into totals[out:out + 4]; `at_rotations`: the elements' energies
    from the FEM's rotations, which must be those of the state (a step's start); `tol`: the
    rotations' (tissue.fem.energy.element_energy)."""
    _keep_state(k, w, previous, edited)
    if w.totals[FRESH] != 0:
        total = 0.0
        for e in range(k.counts[1]):
            if ti.static(at_rotations):
                total += element_energy_at_rotations(k, k, e, k.x, rotation, tol)
            else:
                total += element_energy(k, e, k.x, rotation, tol)
        w.totals[ELASTIC] = total
    _close_evaluation(k, w, out)


@ti.kernel
def _energy(k: STEP, w: ENERGY_WORK, rotation: ti.template(), accumulation: ti.template(), parallel: ti.template(),
            previous: ti.i32, edited: ti.i32, product: ti.i32, tol: ti.f64):
    """(kinetic + elastic, the potential of gravity and the applied forces, 1 if the elastic
    energy was evaluated afresh) at the solver's state, into w.totals[AT_END:]; the state is kept
    in slot 1 − previous and compared with slot `previous` (the elastic energy reused where equal
    and not `edited`). Where `product`, also w.stiffness_direction = Σ R Kₑ Rᵀ w.direction, the
    stiffness of the solver's last linearisation (its rotations) times w.direction."""
    if ti.static(parallel):
        ti.loop_config(serialize=True)
        for _ in range(1):
            _keep_state(k, w, previous, edited)
        for e in range(k.counts[1]):
            if w.totals[FRESH] != 0:
                w.per_element[e] = element_energy(k, e, k.x, rotation, tol)
            if product != 0:
                corotational.scatter_element(k, k, "stiffness", e, w.direction, accumulation, rotation)
        for v in range(k.counts[0]):
            if product != 0:
                w.stiffness_direction[v] = -corotational.gathered(k, k, v, accumulation)
        ti.loop_config(serialize=True)
        for _ in range(1):
            if w.totals[FRESH] != 0:
                total = 0.0
                for e in range(k.counts[1]):
                    total += w.per_element[e]
                w.totals[ELASTIC] = total
            _close_evaluation(k, w, AT_END)
    else:
        ti.loop_config(serialize=True)
        for _ in range(1):
            _evaluate_serial(k, w, rotation, False, previous, edited, AT_END, tol)
            if product != 0:
                corotational.scatter(k, k, "stiffness", w.direction, accumulation, rotation)
                for v in range(k.counts[0]):
                    w.stiffness_direction[v] = -corotational.gathered(k, k, v, accumulation)


@compilation.without_ir_passes(inlines_multigrid)
@ti.kernel
def _checked_serial(k: STEP, o: ti.template(), w: ENERGY_WORK, tol: ti.f64, previous: ti.i32,
                    edited: ti.i32):
    """The serial step (tissue.solver.step_kernels._serial) with an evaluation at its start, after
    its rotations, and one at its end (w.totals[AT_START:] and [AT_END:]): the start's state kept in
    slot 1 − previous, the end's in slot `previous`."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        begin(k, o, tol)
        _evaluate_serial(k, w, o.rotation, True, previous, edited, AT_START, tol)
        solve_serial(k, o)
        end(k)
        _evaluate_serial(k, w, o.rotation, False, 1 - previous, 0, AT_END, tol)


ENERGY, CHECKED_SERIAL = replayed(_energy), replayed(_checked_serial)


class EnergyControl:
    """Energy-checked steps of one ImplicitEuler (its `dt`, gravity and applied forces)."""

    def __init__(self, solver, tolerance: float = TOLERANCE, max_halvings: int = MAX_HALVINGS, fused: bool = True,
                 budget: bool = False):
        if not tolerance >= 0:
            raise TissueError(f"tolerance: must be ≥ 0, got {tolerance!r}")
        if not (isinstance(max_halvings, int) and max_halvings >= 0):
            raise TissueError(f"max_halvings: must be an integer ≥ 0, got {max_halvings!r}")
        self.solver, self.tolerance, self.max_halvings = solver, tolerance, max_halvings
        # Where the solver runs serially, the evaluations in the step's launch (False: launches of
        # their own, as elsewhere; the benchmarks' and tests' comparison).
        self.fused = fused
        self.evaluations = 0        # elastic energies evaluated afresh (the others reused)
        self._work = self._totals_view = self._product_views = None
        self._shape = None          # the model's capacities the work is sized for
        self._edits = None          # the model's edit count at the last evaluation
        self._slot = 0              # where the last evaluation kept its state
        self._first_start = None    # (kinetic + elastic, potential) at the current step's start
        self._first_terms = None    # and Σ|terms| of its energy there
        self._start_terms = None    # Σ|terms| at the start of the last step taken, where evaluated
        self.terms = 0.0            # Σ|terms| of the last evaluation's energy (its rounding's scale)
        self._solves = []           # the budget's measures of the current step's kept solves
        self.budget = EnergyBudget(self) if budget else None     # its step's end projected onto it

    def _work_pack(self):
        model = self.solver.model
        shape = (model.node_capacity, model.element_capacity)
        if shape != self._shape:
            real = backend.current().real
            vec3 = ti.types.vector(3, real)
            self._work = ENERGY_WORK(per_element=ti.ndarray(real, shape[1]), seen_x=ti.ndarray(vec3, (2, shape[0])),
                                     seen_v=ti.ndarray(vec3, (2, shape[0])), totals=ti.ndarray(real, TOTALS),
                                     direction=ti.ndarray(vec3, shape[0]),
                                     stiffness_direction=ti.ndarray(vec3, shape[0]))
            self._shape, self._edits = shape, None
            on_cpu = backend.current().arch == "cpu"
            self._totals_view = host_view(self._work.totals) if on_cpu else None
            self._product_views = ((host_view(self._work.direction), host_view(self._work.stiffness_direction))
                                   if on_cpu else None)
        return self._work

    def _totals(self) -> np.ndarray:
        """The evaluations' totals where the launches left them: on the CPU in the array's own
        memory (Taichi reads a kernel's return values one call at a time)."""
        if self._totals_view is not None:
            return self._totals_view
        return self._work.totals.to_numpy()

    def _edited(self) -> int:
        """1 if the model was edited since the last evaluation (its energy not to be reused)."""
        edited = int(self._edits != self.solver.model.edits)
        self._edits = self.solver.model.edits
        return edited

    def energy(self, times: np.ndarray | None = None) -> tuple[float, float]:
        """(kinetic + elastic, the potential of gravity and the applied forces) at the solver's
        state; with `times` (n, 3), also the stiffness of the solver's last step (Σ R Kₑ Rᵀ at
        its rotations) times it, in the same launch, then read by `stiffness_product()`."""
        solver = self.solver
        k = solver._step_pack()
        w = self._work_pack()
        if times is not None:
            self._write_direction(times)
        ENERGY(k, w, solver.fem.rotation, solver.fem.accumulation, solver.execution != "serial", self._slot,
               self._edited(), int(times is not None), solver.fem.rotation_tolerance)
        inner, potential, fresh, self.terms = (float(t) for t in self._totals()[AT_END:AT_END + 4])
        self._slot = 1 - self._slot
        self.evaluations += int(fresh)
        return inner, potential

    def _write_direction(self, values: np.ndarray) -> None:
        n = self.solver.model.n_nodes
        if self._product_views is None:
            padded = np.zeros((self._shape[0], 3), dtype=real_numpy())
            padded[:n] = values
            self._work.direction.from_numpy(padded)
        else:
            self._product_views[0][:n] = values

    def stiffness_product(self) -> np.ndarray:
        """(n, 3): the product the last `energy(times=...)` took."""
        n = self.solver.model.n_nodes
        if self._product_views is None:
            return self._work.stiffness_direction.to_numpy()[:n].astype(np.float64)
        return self._product_views[1][:n].astype(np.float64)

    def _previous_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The state the evaluation before the last one saw (a step's start, after its end)."""
        n, slot = self.solver.model.n_nodes, 1 - self._slot
        w = self._work
        return (w.seen_x.to_numpy()[slot, :n].astype(np.float64), w.seen_v.to_numpy()[slot, :n].astype(np.float64))

    def step(self) -> None:
        solver = self.solver
        dt = solver.dt
        rejections = [0, 0]
        # The budget opens on the step's start: its state kept now, its energy the first
        # evaluation's (in the step's own launch where fused).
        start_state = (solver.positions(), solver.velocities()) if self.budget else None
        self._first_start, self._solves = None, []
        try:
            end = self._advance(None, dt, 0, rejections)
        finally:
            if solver.dt != dt:
                solver.set_parameters(dt=dt)
        solver.stats.count(energy_rejections=rejections[0], energy_unresolved=rejections[1])
        if self.budget:
            self.budget.open(self._first_start, start_state, self._solves, self._first_terms)
            self.budget.close(end)

    def _advance(self, start, dt, depth, rejections):
        """Step over dt from the solver's state (whose energy is `start`, or None where not yet
        evaluated); return the energy at the end."""
        solver = self.solver
        if solver.dt != dt:
            solver.set_parameters(dt=dt)
        start, end = self._checked_step(start)
        if self._first_start is None:
            self._first_start, self._first_terms = start, self._start_terms
        gain = (end[0] + end[1]) - (start[0] + start[1])
        within = gain <= self.tolerance * max(start[0], end[0])
        if within or depth == self.max_halvings:     # kept (counted where still gaining)
            rejections[1] += int(not within)
            if self.budget:
                self._solves.append(solve_residual(solver))
            return end
        rejections[0] += 1
        solver.set_state(*self._previous_state())
        middle = self._advance(None, dt / 2, depth + 1, rejections)
        return self._advance(middle, dt / 2, depth + 1, rejections)

    def _checked_step(self, start):
        """One step of the solver: (the energy at its start, at its end); Σ|terms| of the start's
        in `_start_terms` where evaluated (else None)."""
        solver = self.solver
        if not (self.fused and solver.execution == "serial" and not solver.split_stages):
            self._start_terms = None
            if start is None:
                start, self._start_terms = self.energy(), self.terms
            solver.step()
            return start, self.energy()
        k, o, tol = solver.prepare_step()     # one launch: the evaluations, start and end, in the step's
        with solver.stats.stage("step"):
            CHECKED_SERIAL(k, o, self._work_pack(), tol, self._slot, self._edited())
        t = [float(t) for t in self._totals()[AT_START:AT_END + 4]]   # (inner, potential, fresh, Σ|terms|) twice
        self.evaluations += int(t[2]) + int(t[6])
        self._start_terms, self.terms = t[3], t[7]
        solver.record_step(solver.report())
        return (t[0], t[1]), (t[4], t[5])
