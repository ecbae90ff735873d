"""How the haptic process keeps its ticks: the wait to each deadline and what it asks of the OS.

Each knob below is measured by bench/haptics (its `tuning` ablation: period p99 and max at each
constraint band, the loop's CPU, and the simulation's step, with and without it); the defaults are
what helped there.

- sleep: "hybrid" sleeps to `spin` s before the deadline and spins the rest (the scheduler wakes a
  sleeper late: tens of µs at real-time priority, a time slice of others at normal priority on a
  loaded machine); "sleep" only sleeps (no spin: the least CPU, the latest wake); "spin" never
  sleeps (a whole core, and at normal priority the scheduler then treats the loop as a CPU hog).
- absolute: the sleep is clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME) to the deadline itself
  (nothing between reading the clock and sleeping can make it late), else time.sleep(left).
- collect_garbage: False freezes Python's objects after set-up and turns the cyclic collector off
  in the loop's process (a full collection walks every object Taichi and numpy made: many ticks'
  worth at once; the log's `priority` line gives its time);
  reference counting still frees the loop's per-tick objects, which hold no cycles (the loop
  reports what a final collection found).
- lock_memory: malloc told to keep its heap (no trimming, no mmap below 16 MB: a tick's
  temporaries reuse pages already touched instead of faulting new ones in), then
  mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) once the loop's buffers are allocated and
  touched: what is resident stays so (no swap-in, no code page reclaimed and read again inside a
  tick). Without MCL_ONFAULT, mlockall made Taichi's reserved arena resident: gigabytes, paged in at
  start (Linux; mlockall needs root or a large RLIMIT_MEMLOCK).
- timer_slack_ns: the thread's timer slack (prctl PR_SET_TIMERSLACK; 50 µs by default at normal
  priority: a sleep may end that much late, on purpose, to batch wake-ups).
- slice_us: at normal priority, the thread's scheduling slice (sched_setattr's sched_runtime, read
  by Linux ≥ 6.12's EEVDF scheduler as the task's requested slice): a short slice gives the woken
  loop an earlier virtual deadline, so it preempts the running task instead of waiting for its
  slice to end. No privilege is needed; older kernels ignore it. Off by default: measured, a
  slice shorter than a tick's work got the loop preempted inside its ticks far more often than
  the kernel's slice did, for no better rate (bench.haptics's `tuning` ablation).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import time
from dataclasses import dataclass

from ..errors import TissueError

CLOCK_MONOTONIC, TIMER_ABSTIME = 1, 1
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
PR_SET_TIMERSLACK = 29
SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}


@dataclass(frozen=True)
class Tuning:
    """The haptic process's timing knobs (see the module docstring)."""

    sleep: str = "hybrid"
    spin: float = 6e-5
    absolute: bool = True
    collect_garbage: bool = False
    lock_memory: bool = True
    timer_slack_ns: int | None = 1
    slice_us: float | None = None

    def __post_init__(self):
        if self.sleep not in ("hybrid", "sleep", "spin"):
            raise TissueError(f"tuning.sleep: one of hybrid, sleep, spin; got {self.sleep!r}")
        if not (0.0 <= self.spin <= 1e-2):
            raise TissueError(f"tuning.spin: between 0 and 0.01 s, got {self.spin!r}")
        if self.slice_us is not None and not (100.0 <= self.slice_us <= 100_000.0):
            raise TissueError(f"tuning.slice_us: between 100 and 100000 µs (the kernel's bounds), got {self.slice_us!r}")

    def changed(self, **fields) -> "Tuning":
        from dataclasses import replace

        return replace(self, **fields)


_libc = None


def _c():
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    return _libc


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _SchedAttr(ctypes.Structure):
    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32), ("sched_flags", ctypes.c_uint64),
                ("sched_nice", ctypes.c_int32), ("sched_priority", ctypes.c_uint32),
                ("sched_runtime", ctypes.c_uint64), ("sched_deadline", ctypes.c_uint64),
                ("sched_period", ctypes.c_uint64), ("sched_util_min", ctypes.c_uint32),
                ("sched_util_max", ctypes.c_uint32)]


def sleeper(tuning: Tuning):
    """A function sleep_until(deadline) (deadline on time.monotonic's clock) as `tuning` says."""
    spin = 0.0 if tuning.sleep == "sleep" else tuning.spin
    clock = time.monotonic

    def spin_until(deadline):
        while clock() < deadline:
            pass

    if tuning.sleep == "spin":
        return spin_until
    if tuning.absolute:
        nanosleep, spec = _c().clock_nanosleep, _Timespec()
        ref = ctypes.byref(spec)

        def sleep_until(deadline):
            wake = deadline - spin
            if wake > clock():
                spec.tv_sec = int(wake)
                spec.tv_nsec = int((wake - spec.tv_sec) * 1e9)
                nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, ref, None)
            spin_until(deadline)
    else:
        def sleep_until(deadline):
            left = deadline - clock() - spin
            if left > 0:
                time.sleep(left)
            spin_until(deadline)
    return sleep_until


def apply(tuning: Tuning, realtime: bool, cpu: int | None) -> list[str]:
    """Set up this process as `tuning`, `realtime` (SCHED_FIFO 10) and `cpu` (a core) ask, before
    its loop starts (after its buffers are allocated and touched); returns what was done or
    refused, in words."""
    done = []
    if realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            done.append("realtime (SCHED_FIFO 10)")
        except (PermissionError, AttributeError, OSError):
            done.append("normal (real-time priority refused)")
    else:
        done.append("normal")
        if tuning.slice_us is not None:
            done.append(_set_slice(tuning.slice_us))
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
            done.append(f"on core {cpu}")
        except (AttributeError, OSError):
            done.append(f"core {cpu} refused")
    if tuning.timer_slack_ns is not None:
        ok = _c().prctl(PR_SET_TIMERSLACK, int(tuning.timer_slack_ns), 0, 0, 0) == 0
        done.append(f"timer slack {tuning.timer_slack_ns} ns" + ("" if ok else " refused"))
    if not tuning.collect_garbage:
        began = time.monotonic()
        gc.collect()                # (what a full collection would cost inside a tick, said)
        spent = time.monotonic() - began
        gc.freeze()
        gc.disable()
        done.append(f"GC frozen and off (a full collection took {1e3 * spent:.0f} ms)")
    if tuning.lock_memory:
        libc = _c()
        libc.mallopt(M_TRIM_THRESHOLD, 1 << 30)
        libc.mallopt(M_MMAP_THRESHOLD, 1 << 24)
        ok = libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0
        done.append("memory locked" if ok else f"mlockall refused (errno {ctypes.get_errno()})")
    done.append(f"sleep {tuning.sleep}" + (f", spin {1e6 * tuning.spin:.0f} µs" if tuning.sleep == "hybrid" else "")
                + (", absolute deadlines" if tuning.absolute and tuning.sleep != "spin" else ""))
    return done


def _set_slice(slice_us: float) -> str:
    number = SYS_SCHED_SETATTR.get(os.uname().machine)
    if number is None:
        return "slice: sched_setattr unknown on this machine"
    attr = _SchedAttr(size=ctypes.sizeof(_SchedAttr), sched_policy=0, sched_nice=os.getpriority(os.PRIO_PROCESS, 0),
                      sched_runtime=int(slice_us * 1e3))
    if _c().syscall(number, 0, ctypes.byref(attr), 0) != 0:
        return f"slice {slice_us:.0f} µs refused (errno {ctypes.get_errno()})"
    return f"slice {slice_us:.0f} µs"
