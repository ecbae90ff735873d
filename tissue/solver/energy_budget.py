"""The energy budget (Dinev et al. 2018, "Stabilizing integrators for real-time physics"): no step
ends with more energy than it started with plus the work done on the body in it, beyond what the
solvers' own accuracy lets a step gain (its allowance), and those allowances add up over the
last WINDOW steps' at most (the ledger, below).

"large" (edge-frame) forces are not the gradient of an energy, so a step can gain energy that no
step size removes; the energy check (tissue.solver.step_control) halves a step that gains more
than its tolerance, and the gains under it add up (the abrupt twist of the stability matrix:
0.035 energy scales over 250 steps). The budget removes each step's gain outright.

The energy E is the energy check's: kinetic + elastic + the potential of gravity and the applied
forces (their work is its fall). A step's budget is E at its start plus the work the contact
stage's moving obstacles did on the body (`add_work`; static obstacles and held nodes do none)
plus what is left of its allowance a (below). `close()` compares E at the step's end with it and,
where it is over, projects the state back onto the budget:

  - the kinetic energy K takes the excess when it holds it: v ← s v, s = √(1 − excess / K);
  - else the state goes back along the step toward its start (x₀ + s (x − x₀), s v), to an s in
    [0, 1] where the rest of the energy, U = E − K (elastic + potential: K is s² K there), is within
    the budget, and then the velocities are scaled as above. U along the step is smooth (elastic
    energy near quadratic, potential linear), so s is found by regula falsi (`_crossing`).

A step whose start itself is over the budget (an obstacle took work out) ends at its start, at
rest (`budget_unresolved`). The solver's stats count `budget_projections` (closes that changed the
state), `budget_removed` (J), `budget_allowance` (a, J), `budget_ledger` (D after it, J) and
`budget_correction` (the correction's residual work below, J).
Costs: a copy of x and v at each step's start, a read of r and two of v (host views on the CPU),
after a contact correction Hᵀλ and a stiffness product (below), and, per projected step, a
velocity write (and the search's energy launches when the kinetic energy cannot absorb it).

The allowance. Implicit Euler on its linearised model (A dv = b, tissue.solver.implicit_euler)
loses energy exactly: with the step's extra impulses s (what A dv − b is beyond the forces),

    E(x₁, v₁) − E(x₀, v₀) = −½ dvᵀM dv − ½ h² v₁ᵀK v₁ − h v₁ᵀB v₁ + v₁ · s + N,

N the co-rotational energy's departure from its quadratic model over the step (second order in
the motion). A real gain is N, or a step too large for the linearisation; v₁ · s is the solvers'
inexactness, what a body at rest on a floor shows (SOFA's floor scene, bench/contact.py, settled:
v₁ · s = 2-3.5e-9 J a step, the dissipation 0.8-2.5e-9, N 1e-14: the step ends 0.3-2.3e-9 J up).
Its parts, each bounded by what the step knows:

  - CG's residual r = b − A dv (`ImplicitEuler.residual`) is an impulse −r the solve left
    unbalanced, whose work is −r · v, v the velocity at the solve's end: the step's end (after the
    contact correction) for its last solve, the half step's for the energy check's earlier halves
    (`solve_residual`, with `open`). Their sum is computed, not bounded: through norms,
    ‖M^-½ r‖ ‖M^½ v‖, it was 10× the sum on the abrupt twist (3.8e-4 of its energy a step, at CG's
    1e-3). A capped CG (SOFA's 25 iterations, ‖r‖/‖b‖ ~ 0.13 at rest on the floor) is about half
    of v₁ · s there.
  - The contact reactions λ (impulses) do the work λ · H v₁ = Σ λᵢ · (δᵢ(end) − δᵢ(start)) / h;
    exact reactions do none where their contact touches at both ends (complementarity) and only
    lose where they slide (Coulomb's law). The solver meets each contact's constraints to within
    its natural-map residual, at most `tolerance` (m), at the step's end, as the last step's solve
    did at its start: a reaction's work beyond the exact one's is at most |λᵢ| / h times tolerance
    at each end, 2 tolerance Σ |λᵢ| / h (`tissue.contact.layer.contact_allowance`, `add_allowance`).
    A reaction of a contact apart is itself within the residual and is not counted.
  - The contact correction's own residual. The correction moves the velocities by dv_c, which
    should solve A dv_c = Hᵀλ (tissue.contact.compliance); so s = −r + Hᵀλ + (A dv_c − Hᵀλ), and
    the last term, the correction's residual, works on v₁ as CG's does: v₁ · (A dv_c − Hᵀλ),
    computed, not bounded (`add_correction`, `correction_work`). The warped compliance solves it
    with nodal rotations in place of the elements' (A ≈ R A₀ Rᵀ), so it is not small: ~1e-10 J a
    step on the settled floor scene, −0.8 to +3.8e-6 J on the stability matrix's clamped beam
    resting on its floor (up to 5× the contact part there); the exact compliance, a factorisation
    of this A, leaves rounding. A is the matrix of the step's last solve (its rotations) at the
    step's dt (after halved steps, the dt the contact stage corrected with). The two computed
    works make one sum, the work of s − Hᵀλ (the halves' at their own velocities), which the
    allowance takes where > 0. dv_c is the velocities' change between the free motion's close
    and the contact close, which only the correction makes in a step (velocities raised there by
    anything else would pass as its own). Cost: K dv_c, a stiffness product in the energy
    evaluation the close makes anyway (tissue.solver.step_control), and a read of v.
  - Rounding: E is a fixed-order sum of n terms (each node's kinetic and potential energy, each
    element's elastic energy), each good to a few ε of itself, the sum to (n − 1) ε Σ|terms|
    (Higham); at both ends of the step: 2 n ε (Σ|terms| at the start + at the end), Σ|terms|
    summed by the energy's own kernel (tissue.solver.step_control).

Non-accumulation: the ledger D is what accepted steps gained above their budgets' base (E at the
start plus the work), less what later steps lost, never below 0: D ← max(0, D + E(end) − E(start) −
work). Its ceiling is the sum of the allowances of the last WINDOW steps, this one's included, and
a step may gain its own allowance as far as D stays under it: the budget is E(start) + work +
min(a, ceiling − D). So at every step's end E ≤ E(first start) + the work done + D (the reference
E − D only falls or takes the work; a step counted `budget_unresolved` is over it by what its
obstacle took beyond the kinetic energy), and D only grows while under the ceiling of the recent
steps: a steady gain is stopped once D meets it, after WINDOW allowances at most; losses pay D
back, so a body at rest, its steps gaining and losing by turns, keeps its room; and a large
allowance leaves the ceiling WINDOW steps later: a D it let in stays until losses pay it back, no
later gain can use it.
Why a window's sum. The largest allowance of a step so far (the ceiling before) held the stability
matrix's clamped beam resting on its floor at 243 of 250 steps: each step gains within its
allowance (its correction's residual work, above), but the energy creeps up by ~1.5e-5 J over
~25 steps (~8 allowances) and back without the budget, the solver's error carried until the
beam slips and gives it back; and one early allowance (an impact's) widened the bound for ever. Windows of 1, 4,
8, 12, 16 steps held that beam at 243, 236, 133, 4, 0 of its 250 steps (python -m bench.stability
cell "rest clamped", polar). A window of one (each step's own allowance) held the liver on the floor
after a transient of cold warm starts, until losses paid D back.
"""

from collections import deque

import numpy as np

from .. import backend
from ..errors import TissueError

PRECISION = 1e-3    # of the excess: the most the search back along the step removes beyond it
SEARCHES = 20       # energy evaluations at most in that search
WINDOW = 16         # steps whose allowances the ledger's ceiling sums (module docstring)
EPSILON = {"f64": float(np.finfo(np.float64).eps), "f32": float(np.finfo(np.float32).eps)}


def solve_residual(solver) -> tuple[np.ndarray, float]:
    """(r, −r · v) after a solve of `solver`: its CG residual (n, 3) and the work of the impulse
    −r on the velocity at the solve's end (J)."""
    r = solver.residual()
    return r, -float((r * solver.velocities()).sum())


class EnergyBudget:
    """The energy budget of one body, on the energy of its EnergyControl (`control`)."""

    def __init__(self, control):
        self.control = control
        self.solver = control.solver
        self.epsilon = EPSILON[backend.current().precision]
        self.allowed = None       # the energy the current step may end with before its allowance (J)
        self.ledger = 0.0         # D (J): accepted gains above the budgets' base not yet lost again
        self.ceiling = 0.0        # D's bound at the last close (J): the window's allowances summed
        self._allowances = deque(maxlen=WINDOW)     # of the last WINDOW steps, this one's last
        self._ledger_open = 0.0   # D at the current step's start
        self._contact = 0.0       # the contact stage's part of the allowance (J)
        self._correction = None   # Hᵀλ (n, 3, N·s) of a contact correction since the last close
        self._closed = None       # the velocities the last close of this step left
        self._solves = ()         # (r, −r · v at its end) of the step's solves
        self._start = None        # (x, v) at its start
        self._start_energy = 0.0  # E there (J)
        self._start_terms = 0.0   # Σ|terms| of E there (J): its rounding's scale

    def open(self, start: tuple[float, float], state=None, solves=(), terms: float | None = None) -> None:
        """A step begins at the solver's state, whose (kinetic + elastic, potential) is `start`,
        at `state`, (positions, velocities) (default: the solver's now); `solves`: its solves'
        `solve_residual`s, in order; `terms`: Σ|terms| of the start's energy (default: the last
        evaluation's, `start`'s where the caller just evaluated it)."""
        self.allowed = self._start_energy = start[0] + start[1]
        self._start = (self.solver.positions(), self.solver.velocities()) if state is None else state
        self._start_terms = self.control.terms if terms is None else terms
        self._ledger_open, self._contact, self._solves = self.ledger, 0.0, tuple(solves)
        self._correction = self._closed = None
        self._allowances.append(0.0)

    def add_work(self, joules: float) -> None:
        """Work done on the body during the step by what the energy does not hold (moving obstacles)."""
        self.allowed += joules

    def add_allowance(self, joules: float) -> None:
        """A bound on the energy another stage's inexact solve may have added in the step (the
        contact reactions')."""
        self._contact += joules

    def add_correction(self, impulses: np.ndarray) -> None:
        """The nodal impulses Hᵀλ (n, 3) of a contact correction that moved the velocities since
        this step's last close: the allowance takes the work of its own residual A dv_c − Hᵀλ."""
        if self._closed is None:
            raise TissueError("add_correction: the step's free motion was not closed before its correction")
        self._correction = impulses

    def correction_work(self) -> tuple[tuple[float, float], float]:
        """(the energy at the solver's state as `control.energy()` gives it, the work
        v₁ · (A dv_c − Hᵀλ) of the correction's residual), in one energy launch, which takes
        K dv_c too; dv_c: the velocities' change since the last close, A: the implicit matrix
        of the step's last solve (its rotations, the step's dt)."""
        solver = self.solver
        v = solver.velocities()
        dv = v - self._closed
        energy = self.control.energy(times=dv)
        A_dv = (solver.mass_factor * solver.model.mass[:, None] * dv
                + solver.stiffness_factor * self.control.stiffness_product())
        return energy, float((v * (A_dv - self._correction)).sum())

    def allowance(self, correction: float | None = None) -> float:
        """a (J) at the solver's state, its energy the control's last evaluation (module
        docstring); `correction`: the work of the correction's residual where known (else
        `correction_work()`'s, where there is a correction)."""
        solver = self.solver
        cg = sum(work for _, work in self._solves[:-1])
        if self._solves:
            cg -= float((self._solves[-1][0] * solver.velocities()).sum())
        if correction is None and self._correction is not None:
            correction = self.correction_work()[1]
        terms = solver.model.n_nodes + solver.model.n_elements
        rounding = 2 * terms * self.epsilon * (self._start_terms + self.control.terms)
        return max(0.0, cg + (correction or 0.0)) + self._contact + rounding

    def room(self, allowance: float) -> float:
        """What the step may end with above its budget's base, its allowance `allowance`:
        min(a, ceiling − D), the ceiling counting a (module docstring)."""
        return max(0.0, min(allowance, self._ceiling(allowance) - self._ledger_open))

    def _ceiling(self, allowance: float) -> float:
        """The window's allowances summed, this step's being `allowance`."""
        return sum(list(self._allowances)[:-1], allowance)

    def close(self, end: tuple[float, float] | None = None) -> None:
        """Project the step's end onto the budget; `end`: its (kinetic + elastic, potential) if
        known (else evaluated)."""
        correction = None
        if self._correction is not None:
            end, correction = self.correction_work()
        inner, potential = self.control.energy() if end is None else end
        allowance = self.allowance(correction)
        self._correction = None
        budget = self.allowed + self.room(allowance)
        self.ceiling, self._allowances[-1] = self._ceiling(allowance), allowance
        energy = inner + potential
        excess = energy - budget
        solver = self.solver
        if excess <= 0.0:
            self.ledger = max(0.0, self._ledger_open + energy - self.allowed)
            solver.stats.count(budget_projections=0, budget_removed=0.0, budget_unresolved=0,
                               budget_allowance=allowance, budget_ledger=self.ledger,
                               budget_correction=correction or 0.0)
            self._closed = solver.velocities()
            return
        x, v = solver.positions(), solver.velocities()
        kinetic = self._kinetic(v)
        removed, unresolved, ends_with = excess, 0, budget
        if kinetic < excess:
            x, v, excess, unresolved, ends_with = self._back_along_step(x, v, kinetic, excess, budget)
            kinetic = self._kinetic(v)
        if excess > 0.0 and kinetic > 0.0:
            v = v * np.sqrt(max(0.0, 1.0 - excess / kinetic))
        solver.set_state(x, v)      # not evaluated: the next evaluation, if any, finds it changed
        self._closed = v
        self.ledger = max(0.0, self._ledger_open + ends_with - self.allowed)
        solver.stats.count(budget_projections=1, budget_removed=removed, budget_unresolved=unresolved,
                           budget_allowance=allowance, budget_ledger=self.ledger,
                           budget_correction=correction or 0.0)

    def _kinetic(self, v) -> float:
        return 0.5 * float(self.solver.model.mass @ (v * v).sum(1))

    def _back_along_step(self, x, v, kinetic, excess, budget):
        """(x, v, excess, unresolved, energy) at an s with U(x₀ + s (x − x₀)) within `budget` (U = E − K,
        K = `kinetic` at the end,
        the energy less the kinetic, which s² K keeps) by at most PRECISION of `excess` (the end's,
        s = 1), so that at most (1 + PRECISION) times the excess is removed; the excess left there
        goes to the kinetic energy; `energy`: what the state ends with once it has."""
        solver, (x0, v0) = self.solver, self._start

        def over(s):    # U − the budget at s (evaluated at rest: U is the energy there)
            solver.set_state(x0 + s * (x - x0))
            inner, potential = self.control.energy()
            return inner + potential - budget

        solver.set_state(velocities=np.zeros_like(v))
        f_low = self._start_energy - self._kinetic(v0) - budget     # U at the start: E less K
        if f_low > 0.0:              # the start is over the budget: kept, at rest
            return x0, np.zeros_like(v), 0.0, 1, budget + f_low
        low, f_low = _crossing(over, f_low, excess - kinetic, PRECISION * excess)
        left = f_low + low * low * kinetic      # over the budget there (the velocities take it if > 0)
        return x0 + low * (x - x0), low * v, max(left, 0.0), 0, budget + min(left, 0.0)


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
