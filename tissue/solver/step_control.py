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
The stats also count the step's rejections (`energy_rejections`). Costs: an energy evaluation on
the host (the principal stretches of every element) at the end of each step, and at its start
unless the state is the one the last step ended at (the contact stage's correction moves it), and
the rejected steps' work (bench/step_control.py).
"""

from __future__ import annotations

import numpy as np

from ..errors import TissueError
from ..fem.energy import elastic_energy

TOLERANCE = 1e-3        # of the energy in play (kinetic + elastic), the most a step may gain
MAX_HALVINGS = 6        # dt / 64 at the finest


class EnergyControl:
    """Energy-checked steps of one ImplicitEuler (its `dt`, gravity and applied forces)."""

    def __init__(self, solver, tolerance: float = TOLERANCE, max_halvings: int = MAX_HALVINGS):
        if not tolerance >= 0:
            raise TissueError(f"tolerance: must be ≥ 0, got {tolerance!r}")
        if not (isinstance(max_halvings, int) and max_halvings >= 0):
            raise TissueError(f"max_halvings: must be an integer ≥ 0, got {max_halvings!r}")
        self.solver, self.tolerance, self.max_halvings = solver, tolerance, max_halvings
        self._last = None       # the last kinetic + elastic energy evaluated, and what it depends on

    def energy(self, x: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        """(kinetic + elastic, the potential of gravity and the applied forces) at (x, v)."""
        solver = self.solver
        model = solver.model
        key = (x, v, model.mass, model.tets, model.elastic, model.Dm_inv)
        if self._last is not None and all(a.shape == b.shape and np.array_equal(a, b) for a, b in zip(key, self._last[0])):
            inner = self._last[1]           # a step's start where the last one ended
        else:
            inner = 0.5 * float(model.mass @ (v * v).sum(1)) + elastic_energy(model, x, solver.fem.rotation)
        potential = -float(model.mass @ (x @ np.asarray(solver.gravity, dtype=np.float64)))
        potential -= float((solver.external_forces() * x).sum())
        self._last = (tuple(np.array(a) for a in key), inner)
        return inner, potential

    def step(self) -> None:
        solver = self.solver
        dt = solver.dt
        x, v = solver.positions(), solver.velocities()
        rejections = [0, 0]
        try:
            self._advance(x, v, self.energy(x, v), dt, 0, rejections)
        finally:
            if solver.dt != dt:
                solver.set_parameters(dt=dt)
        solver.stats.count(energy_rejections=rejections[0], energy_unresolved=rejections[1])

    def _advance(self, x, v, start, dt, depth, rejections):
        """Step from (x, v) over dt (the solver's state is there); return the energy at the end."""
        solver = self.solver
        if solver.dt != dt:
            solver.set_parameters(dt=dt)
        solver.step()
        x1, v1 = solver.positions(), solver.velocities()
        end = self.energy(x1, v1)
        gain = (end[0] + end[1]) - (start[0] + start[1])
        if gain <= self.tolerance * max(start[0], end[0]):
            return end
        if depth == self.max_halvings:
            rejections[1] += 1
            return end
        rejections[0] += 1
        solver.set_state(x, v)
        middle = self._advance(x, v, start, dt / 2, depth + 1, rejections)
        xm, vm = solver.positions(), solver.velocities()
        return self._advance(xm, vm, middle, dt / 2, depth + 1, rejections)
