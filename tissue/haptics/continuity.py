"""The force the device is sent: the haptic re-solve made continuous where the simulation hands
over a new step (paper §3.6's inter-sampled forces, without the step's jump).

Between steps the haptic loop re-solves the last step's problem for the device's pose
(tissue.haptics.lcp.HapticSolver). When the next step's problem arrives, it gives a different
force at the same pose: the bodies moved on their own during the step, contacts appeared or
went, the compliance was warped again. Switched to at once, that difference is a jump the hand
feels at every step (measured on liver_grasp: up to 2.7 N, more than the single-rate force's).

So at the hand-over the difference is taken at the pose of the last tick (the new problem re-solved
there to convergence) and kept as an offset on each jaw's spring force, which then shrinks to
zero linearly over the next `spread` ticks (one simulation step's worth). A tick's force changes
by what the device's own motion in one tick makes (at most K |Δx_d| per jaw: a coupling spring
pulled by its target, whatever is behind it) plus |offset| / spread, and the new step's force is
reached one step later. The step's correction is not lost, only spread over a step: what the
simulation's own force is, the device feels after one step instead of a jump.

A tick's time stays bounded: converging the new problem can take several re-solves (of
max_sweeps sweeps each: more than a tick's time in one tick, measured in bench/haptics), so it
takes one per tick, on a second solver, at the previous tick's pose, while the old problem is
still rendered; the tick in which it converges (or after HANDOVER_SOLVES) switches to it. A tick
then costs at most two re-solves, and the new step arrives a few ticks later at worst.
"""

from __future__ import annotations

import numpy as np

from .lcp import HapticForce, HapticProblem, HapticSolver

HANDOVER_SOLVES = 8      # re-solves (of max_sweeps each, one a tick) at most, at the hand-over's pose


class ContinuousForce:
    """A HapticSolver whose new problems are blended in (see the module docstring).

    rate: the loop's rate (Hz); a new problem's difference from the last rendered force fades over
    one of its steps' worth of ticks (`spread`)."""

    def __init__(self, solver: HapticSolver, rate: float):
        self.solver, self.rate, self.spread = solver, float(rate), 1
        self.next = HapticSolver(solver.capacity, solver.max_sweeps, solver.tolerance)   # converges a new problem
        self.pending, self.tries = False, 0
        self.offset = None           # (jaws, 3) N on each jaw's spring, at the hand-over
        self.since = 0               # ticks rendered from the current problem
        self.last = None             # (springs (jaws, 3), position, orientation, jaw) of the last tick

    @property
    def problem(self) -> HapticProblem | None:
        return self.solver.problem

    def warm(self) -> None:
        """Compile (or load) the re-solve and replay it once on both solvers' buffers."""
        self.solver.warm()
        self.next.warm()

    def load(self, problem: HapticProblem) -> None:
        """Take the next step's problem: rendered from the tick where it has converged at the last
        tick's pose (the difference there spread), at once if nothing was rendered yet."""
        if self.last is None or len(self.last[0]) != problem.jaws:
            self.solver.load(problem)
            self.pending, self.since, self.offset = False, 0, None
            self.spread = max(1, round(self.rate * problem.h))
            return
        self.next.load(problem)
        self.pending, self.tries = True, 0

    def _hand_over(self) -> None:
        """One re-solve of the pending problem at the last tick's pose; switch to it if converged."""
        springs, position, orientation, jaw = self.last
        f = self.next.solve(position, orientation, jaw)
        self.tries += 1
        if f.sweeps < self.next.max_sweeps or self.tries >= HANDOVER_SOLVES:
            self.solver, self.next = self.next, self.solver
            self.pending, self.since, self.offset = False, 0, springs - f.springs
            self.spread = max(1, round(self.rate * self.solver.problem.h))

    def solve(self, position, orientation, jaw: float) -> HapticForce:
        """The force to send for the device at this pose: the re-solve's, plus what is left of the
        hand-over's offset."""
        if self.pending:
            self._hand_over()
        f = self.solver.solve(position, orientation, jaw)
        self.since += 1
        if self.offset is not None:
            left = max(0.0, 1.0 - (self.since - 1) / self.spread) * self.offset
            f = f.shifted(left, self.problem.axis @ np.asarray(orientation).T)
        self.last = (f.springs, np.array(position, dtype=np.float64), np.array(orientation, dtype=np.float64),
                     float(jaw))
        return f
