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
is then held to its start's energy plus the work done on it (tissue.solver.energy_budget).

The energy is one kernel launch over the solver's arrays on the device (nothing copied to the
host): a signed principal-stretch eigensolve per element, summed in a fixed order (a per-element
buffer then a serial sum; one thread throughout where the solver runs serially). The kernel keeps
the last two states it evaluated (x, v), alternately: a state equal to the one before, bit for bit,
on an unedited model (`BodyModel.edits`), reuses its elastic energy (a step's start is where the
last one ended, unless the contact stage's correction moved it); and the state a step started
from is there to undo the step. Costs: that launch at the end of each step, and the rejected
steps' work (bench/step_control.py).
"""

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem.energy import element_energy
from ..fem.model import real_numpy
from ..launch import replayed
from .energy_budget import EnergyBudget
from .implicit_euler import GX, GY, GZ, STEP

TOLERANCE = 1e-3        # of the energy in play (kinetic + elastic), the most a step may gain
MAX_HALVINGS = 6        # dt / 64 at the finest

# The kernel's own arrays: per-element energies, the last two states evaluated (slot, node), and
# its totals: the elastic energy of the last evaluation, whether it was fresh, kinetic, potential.
ENERGY_WORK = ti.types.argpack(per_element=ti.types.ndarray(), seen_x=ti.types.ndarray(),
                               seen_v=ti.types.ndarray(), totals=ti.types.ndarray())


@ti.kernel
def _energy(k: STEP, w: ENERGY_WORK, rotation: ti.template(), parallel: ti.template(), previous: ti.i32,
            edited: ti.i32) -> ti.types.vector(3, ti.f64):     # not `float`: read at import, before ti.init
    """(kinetic + elastic, the potential of gravity and the applied forces, 1 if the elastic
    energy was evaluated afresh) at the solver's state; the state is kept in slot 1 − previous
    and compared with slot `previous` (the elastic energy reused where equal and not `edited`)."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        changed = edited
        for v in range(k.counts[0]):
            if (k.x[v] != w.seen_x[previous, v]).any() or (k.v[v] != w.seen_v[previous, v]).any():
                changed = 1
            w.seen_x[1 - previous, v] = k.x[v]
            w.seen_v[1 - previous, v] = k.v[v]
        w.totals[1] = changed
    if ti.static(parallel):
        for e in range(k.counts[1]):
            if w.totals[1] != 0:
                w.per_element[e] = element_energy(k, e, k.x, rotation)
    ti.loop_config(serialize=True)
    for _ in range(1):
        if w.totals[1] != 0:
            total = 0.0
            for e in range(k.counts[1]):
                if ti.static(parallel):
                    total += w.per_element[e]
                else:
                    total += element_energy(k, e, k.x, rotation)
            w.totals[0] = total
        g = ti.Vector([k.parameters[GX], k.parameters[GY], k.parameters[GZ]])
        kinetic, potential = 0.0, 0.0
        for v in range(k.counts[0]):
            kinetic += 0.5 * k.mass[v] * k.v[v].norm_sqr()
            potential -= (k.mass[v] * g + k.external[v]).dot(k.x[v])
        w.totals[2] = kinetic
        w.totals[3] = potential
    return ti.Vector([w.totals[2] + w.totals[0], w.totals[3], w.totals[1]])


ENERGY = replayed(_energy)


class EnergyControl:
    """Energy-checked steps of one ImplicitEuler (its `dt`, gravity and applied forces)."""

    def __init__(self, solver, tolerance: float = TOLERANCE, max_halvings: int = MAX_HALVINGS, budget: bool = False):
        if not tolerance >= 0:
            raise TissueError(f"tolerance: must be ≥ 0, got {tolerance!r}")
        if not (isinstance(max_halvings, int) and max_halvings >= 0):
            raise TissueError(f"max_halvings: must be an integer ≥ 0, got {max_halvings!r}")
        self.solver, self.tolerance, self.max_halvings = solver, tolerance, max_halvings
        self.evaluations = 0        # elastic energies evaluated afresh (the others reused)
        self._work = None
        self._shape = None          # the model's capacities the work is sized for
        self._edits = None          # the model's edit count at the last evaluation
        self._slot = 0              # where the last evaluation kept its state
        self.budget = EnergyBudget(self) if budget else None     # its step's end projected onto it

    def _work_pack(self):
        model = self.solver.model
        shape = (model.node_capacity, model.element_capacity)
        if shape != self._shape:
            real = backend.current().real
            vec3 = ti.types.vector(3, real)
            self._work = ENERGY_WORK(per_element=ti.ndarray(real, shape[1]), seen_x=ti.ndarray(vec3, (2, shape[0])),
                                     seen_v=ti.ndarray(vec3, (2, shape[0])), totals=ti.ndarray(real, 4))
            self._shape, self._edits = shape, None
        return self._work

    def energy(self) -> tuple[float, float]:
        """(kinetic + elastic, the potential of gravity and the applied forces) at the solver's
        state."""
        solver = self.solver
        k = solver._step_pack()
        w = self._work_pack()
        edited = int(self._edits != solver.model.edits)
        inner, potential, fresh = ENERGY(k, w, solver.fem.rotation, solver.execution != "serial", self._slot, edited)
        self._slot, self._edits = 1 - self._slot, solver.model.edits
        self.evaluations += int(fresh)
        return float(inner), float(potential)

    def _previous_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The state the evaluation before the last one saw (a step's start, after its end)."""
        n, slot = self.solver.model.n_nodes, 1 - self._slot
        w = self._work
        return (w.seen_x.to_numpy()[slot, :n].astype(np.float64), w.seen_v.to_numpy()[slot, :n].astype(np.float64))

    def step(self) -> None:
        solver = self.solver
        dt = solver.dt
        rejections = [0, 0]
        start = self.energy()
        if self.budget:
            self.budget.open(start)
        try:
            end = self._advance(start, dt, 0, rejections)
        finally:
            if solver.dt != dt:
                solver.set_parameters(dt=dt)
        solver.stats.count(energy_rejections=rejections[0], energy_unresolved=rejections[1])
        if self.budget:
            self.budget.close(end)

    def _advance(self, start, dt, depth, rejections):
        """Step over dt from the state the last evaluation saw (the solver's state, whose energy
        is `start`); return the energy at the end."""
        solver = self.solver
        if solver.dt != dt:
            solver.set_parameters(dt=dt)
        solver.step()
        end = self.energy()
        gain = (end[0] + end[1]) - (start[0] + start[1])
        if gain <= self.tolerance * max(start[0], end[0]):
            return end
        if depth == self.max_halvings:
            rejections[1] += 1
            return end
        rejections[0] += 1
        solver.set_state(*self._previous_state())
        middle = self._advance(self.energy(), dt / 2, depth + 1, rejections)
        return self._advance(middle, dt / 2, depth + 1, rejections)
