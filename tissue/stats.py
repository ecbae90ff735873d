"""Per-stage wall times and counters of a simulation (host time after `backend.sync()`)."""

from __future__ import annotations

import time
from collections import defaultdict

import numpy as np

from . import backend


class Stats:
    """Times per stage (seconds, one entry per step) and the last value of each counter."""

    def __init__(self):
        self.times: dict[str, list[float]] = defaultdict(list)
        self.counters: dict[str, float] = {}
        self.history: dict[str, list[float]] = defaultdict(list)

    def stage(self, name: str) -> "_Stage":
        """`with stats.stage(name):` appends the block's wall time to times[name] (not when it
        raises)."""
        return _Stage(self.times, name)

    def count(self, **values: float) -> None:
        for key, value in values.items():
            self.counters[key] = value
            self.history[key].append(value)

    def ms_per_step(self, skip: int = 0) -> dict[str, float]:
        """Median milliseconds per step of each stage, leaving out the first `skip` (warm-up)."""
        return {name: 1e3 * float(np.median(t[skip:] if len(t) > skip else t))
                for name, t in self.times.items() if t}

    def table(self, skip: int = 1) -> str:
        ms = self.ms_per_step(skip)
        width = max([len(k) for k in ms] + [5])
        lines = [f"{'stage':<{width}}  ms/step (median)"]
        lines += [f"{k:<{width}}  {v:10.3f}" for k, v in ms.items()]
        lines.append(f"{'total':<{width}}  {sum(ms.values()):10.3f}")
        return "\n".join(lines)


class _Stage:
    """Stats.stage's timer (a class: a generator-based context manager costs several times more a
    use, and a step makes a dozen)."""

    __slots__ = ("times", "name", "start")

    def __init__(self, times: dict, name: str):
        self.times, self.name = times, name

    def __enter__(self):
        self.start = time.perf_counter()

    def __exit__(self, kind, value, traceback):
        # One sync, at the end: stages follow each other, so the previous stage's closing sync
        # already bounds this one's start (a sync costs a few µs, a step of a small mesh 300).
        if kind is None:
            backend.sync()
            self.times[self.name].append(time.perf_counter() - self.start)
