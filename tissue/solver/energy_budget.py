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
  - else the state goes back along the step toward its start (x₀ + s (x − x₀), s v), to an s in
    [0, 1] where the rest of the energy, U = E − K (elastic + potential: K is s² K there), is within
    the budget, and then the velocities are scaled as above. U along the step is smooth (elastic
    energy near quadratic, potential linear), so s is found by regula falsi (`_crossing`).

A step whose start itself is over the budget (an obstacle took work out) ends at its start, at
rest (`budget_unresolved`). The solver's stats count `budget_projections` (steps projected) and
`budget_removed` (J). Costs: a copy of x and v at each step's start, and, per projected step, a
velocity write (and the search's energy launches when the kinetic energy cannot absorb it).

Why a body at rest on a static floor is projected: its contact correction ends a step at rest
slightly above its start, by ~1e-4 of the work gravity does in the step's free motion (the floor
scene of bench/contact.py, CG converged to 1e-12: 3.2e-9 J at every step; no rounding at that
scale; without the budget that run's energy only fluctuates, ±6e-9 J a step). A real gain of the
scheme, and the budget removes it. A CG capped short of convergence (SOFA's 25 iterations) loses
energy in the free motion that hides it on some steps, fewer where it is warm-started (closer to
the converged solve). Once the body has settled (after ~400 steps) nearly every step is projected,
and U rises from the start along the whole step: the step is undone (s = 0), the body held where
it rests, found in 2 evaluations (bisection: 20, each an elastic energy of every element).
"""

import numpy as np

from .. import backend

# A rise within this fraction of the energy in play (kinetic + elastic) is rounding, not a gain.
ROUNDING = {"f64": 1e-10, "f32": 1e-5}
PRECISION = 1e-3    # of the excess: the most the search back along the step removes beyond it
SEARCHES = 20       # energy evaluations at most in that search


class EnergyBudget:
    """The energy budget of one body, on the energy of its EnergyControl (`control`)."""

    def __init__(self, control):
        self.control = control
        self.solver = control.solver
        self.rounding = ROUNDING[backend.current().precision]
        self.allowed = None       # the energy the current step may end with (J)
        self.in_play = 0.0        # kinetic + elastic at its start (J): the rounding's scale
        self._start = None        # (x, v) at its start
        self._start_energy = 0.0  # E there (J)

    def open(self, start: tuple[float, float], state=None) -> None:
        """A step begins at the solver's state, whose (kinetic + elastic, potential) is `start`,
        at `state`, (positions, velocities) (default: the solver's now)."""
        self.allowed, self.in_play = start[0] + start[1], start[0]
        self._start_energy = self.allowed
        self._start = (self.solver.positions(), self.solver.velocities()) if state is None else state

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
            x, v, excess, unresolved = self._back_along_step(x, v, kinetic, excess)
            kinetic = self._kinetic(v)
        if excess > 0.0 and kinetic > 0.0:
            v = v * np.sqrt(max(0.0, 1.0 - excess / kinetic))
        solver.set_state(x, v)      # not evaluated: the next evaluation, if any, finds it changed
        solver.stats.count(budget_projections=1, budget_removed=removed, budget_unresolved=unresolved)

    def _kinetic(self, v) -> float:
        return 0.5 * float(self.solver.model.mass @ (v * v).sum(1))

    def _back_along_step(self, x, v, kinetic, excess):
        """(x, v, excess, unresolved) at an s with U(x₀ + s (x − x₀)) within the budget (U = E − K,
        K = `kinetic` at the end,
        the energy less the kinetic, which s² K keeps) by at most PRECISION of `excess` (the end's,
        s = 1), so that at most (1 + PRECISION) times the excess is removed; the excess left there
        goes to the kinetic energy."""
        solver, (x0, v0) = self.solver, self._start

        def over(s):    # U − the budget at s (evaluated at rest: U is the energy there)
            solver.set_state(x0 + s * (x - x0))
            inner, potential = self.control.energy()
            return inner + potential - self.allowed

        solver.set_state(velocities=np.zeros_like(v))
        f_low = self._start_energy - self._kinetic(v0) - self.allowed     # U at the start: E less K
        if f_low > 0.0:              # the start is over the budget: kept, at rest
            return x0, np.zeros_like(v), 0.0, 1
        low, f_low = _crossing(over, f_low, excess - kinetic, PRECISION * excess)
        return x0 + low * (x - x0), low * v, max(f_low + low * low * kinetic, 0.0), 0


def _crossing(f, f_start: float, f_end: float, precision: float) -> tuple[float, float]:
    """(s, f(s)) with f(s) ≤ 0 where f crosses 0 on [0, 1], f(0) = f_start ≤ 0 < f(1) = f_end known:
    regula falsi (the Illinois variant: a side kept twice in a row has its value halved for the
    secant), its first probe at ½ (f may rise from 0 and still dip below it further along: the
    abrupt twist of bench/stability.py), bisecting where the bracket did not halve in three
    evaluations, every probe at least PRECISION of the bracket from its ends. It stops at a point
    it evaluated with f ≥ −precision, or at 0 where f rises from it (f ≤ precision at the bracket's
    other end), or after SEARCHES evaluations; not at 0 merely because f(0) ≥ −precision (a body
    starting at rest on its budget would never move)."""
    low, high, f_low, f_high = 0.0, 1.0, f_start, f_end
    weights, side = [f_low, f_high], None
    widths = [2.0, 2.0, 2.0]        # the bracket's widths three, two and one evaluations ago
    for evaluation in range(SEARCHES):
        if -f_low <= precision and (low > 0.0 or f_high <= precision):
            break
        width = high - low
        s = (low * weights[1] - high * weights[0]) / (weights[1] - weights[0])
        if evaluation == 0 or width > 0.5 * widths[0]:
            s = 0.5 * (low + high)
        s = min(max(s, low + PRECISION * width), high - PRECISION * width)
        widths = [*widths[1:], width]
        value = f(s)
        if value <= 0.0:
            low, f_low, weights[0] = s, value, value
            if side == 0:
                weights[1] *= 0.5
            side = 0
        else:
            high, f_high, weights[1] = s, value, value
            if side == 1:
                weights[0] *= 0.5
            side = 1
    return low, f_low
