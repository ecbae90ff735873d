"""The energy budget (Dinev et al. 2018, "Stabilizing integrators for real-time physics"): no step
ends with more energy than it started with plus the work done on the body in it.

"large" (edge-frame) forces are not the gradient of an energy, so a step can gain energy that no
step size removes; the energy check (tissue.solver.step_control) halves a step that gains more
than its tolerance, and the gains under it add up (the abrupt twist of the stability matrix:
0.035 energy scales over 250 steps). The budget removes each step's gain outright.

The energy E is the energy check's: kinetic + elastic + the potential of gravity and the applied
forces (their work is its fall). A step's budget is E at its start plus the work the contact
stage's moving obstacles did on the body (`add_work`; static obstacles and held nodes do none).
`close()` compares E at the step's end with it and, where it is over by more than rounding,
projects the state back onto the budget:

  - the kinetic energy K takes the excess when it holds it: v ← s v, s = √(1 − excess / K);
  - else the state goes back along the step toward its start (x₀ + s (x − x₀), s v), the largest
    s in [0, 1] within the budget found by bisection, and then the velocities are scaled as above.

A step whose start itself is over the budget (an obstacle took work out) ends at its start, at
rest (`budget_unresolved`). The solver's stats count `budget_projections` (steps projected) and
`budget_removed` (J). Costs: a copy of x at each step's start, and, per projected step, a
velocity write (and the bisection's energy launches when the kinetic energy cannot absorb it).
"""

import numpy as np

from .. import backend

# A rise within this fraction of the energy in play (kinetic + elastic) is rounding, not a gain.
ROUNDING = {"f64": 1e-10, "f32": 1e-5}
BISECTIONS = 20


class EnergyBudget:
    """The energy budget of one body, on the energy of its EnergyControl (`control`)."""

    def __init__(self, control):
        self.control = control
        self.solver = control.solver
        self.rounding = ROUNDING[backend.current().precision]
        self.allowed = None       # the energy the current step may end with (J)
        self.in_play = 0.0        # kinetic + elastic at its start (J): the rounding's scale
        self._start = None        # x at its start

    def open(self, start: tuple[float, float], positions=None) -> None:
        """A step begins at the solver's state, whose (kinetic + elastic, potential) is `start`,
        at `positions` (default: the solver's now)."""
        self.allowed, self.in_play = start[0] + start[1], start[0]
        self._start = self.solver.positions() if positions is None else positions

    def add_work(self, joules: float) -> None:
        """Work done on the body during the step by what the energy does not hold (moving obstacles)."""
        self.allowed += joules

    def close(self, end: tuple[float, float] | None = None) -> None:
        """Project the step's end onto the budget; `end`: its (kinetic + elastic, potential) if
        known (else evaluated)."""
        inner, potential = self.control.energy() if end is None else end
        excess = inner + potential - self.allowed
        solver = self.solver
        if excess <= self.rounding * max(self.in_play, inner):
            solver.stats.count(budget_projections=0, budget_removed=0.0, budget_unresolved=0)
            return
        x, v = solver.positions(), solver.velocities()
        kinetic = self._kinetic(v)
        removed, unresolved = excess, 0
        if kinetic < excess:
            x, v, excess, unresolved = self._back_along_step(x, v)
            kinetic = self._kinetic(v)
        if excess > 0.0 and kinetic > 0.0:
            v = v * np.sqrt(max(0.0, 1.0 - excess / kinetic))
        solver.set_state(x, v)
        self.control.energy()            # the state the next evaluation compares with
        solver.stats.count(budget_projections=1, budget_removed=removed, budget_unresolved=unresolved)

    def _kinetic(self, v) -> float:
        return 0.5 * float(self.solver.model.mass @ (v * v).sum(1))

    def _back_along_step(self, x, v):
        """(x, v, excess, unresolved) at the largest s with E(x₀ + s (x − x₀), s v) − K within
        the budget, the excess then left to the kinetic energy."""
        solver, x0 = self.solver, self._start

        def excess_at(s):
            solver.set_state(x0 + s * (x - x0), s * v)
            inner, potential = self.control.energy()
            return inner + potential - self.allowed

        kinetic = self._kinetic(v)
        low, low_excess = 0.0, excess_at(0.0)
        if low_excess > 0.0:         # the start is over the budget: kept, at rest
            return x0, np.zeros_like(v), 0.0, 1
        high = 1.0
        for _ in range(BISECTIONS):
            middle = 0.5 * (low + high)
            e = excess_at(middle)
            if e <= middle * middle * kinetic:
                low, low_excess = middle, e
            else:
                high = middle
        return x0 + low * (x - x0), low * v, max(low_excess, 0.0), 0
