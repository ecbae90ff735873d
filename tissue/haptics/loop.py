"""The haptic loop in its own process, fed by the simulation through shared memory.

Why a process: a running Taichi CPU kernel holds Python's GIL (a thread meant to tick every 1 ms
waits until the kernel ends: many ticks behind), so a haptic thread in the simulation's process
would stop at every step. The loop runs in a process started by `spawn` (a fresh interpreter: no copy of the
simulation's Taichi state), with Taichi on one CPU thread, its re-solve kernel compiled (or loaded
from the offline cache) and run once before its clock starts.

Hand-off. After each step the simulation publishes the step's restricted problem
(tissue.haptics.lcp.restrict: W among the instrument's rows and those coupled to them, δ_free, λ, μ,
the rows' blocks on the jaws, the jaws' state) into a SharedRecord; the loop, every tick, reads
the device, writes its pose into a second SharedRecord (the simulation's next step reads it as
the coupling's target), re-solves the newest problem for that pose and sends the force (a new
step's correction blended in over a step: tissue.haptics.continuity).

SharedRecord: two slots, each a header (sequence, length, CRC-32) and a float64 payload, in one
shared-memory block, written in turn under a sequence lock: the writer makes the slot's sequence
odd, writes the payload and its CRC, makes it even; a reader takes the slot with the newest even
sequence, copies its payload and keeps the copy only if the sequence is still the same (x86 keeps
stores in order and loads in order). The reader checks the CRC too, so a torn record that slipped
through would be an error, not a force. Two slots, so that a writer preempted mid-write (at
normal priority on a loaded machine: tens of ms) leaves the previous record whole for the
reader: with one slot, the simulation's read of the device's pose once spun through 100,000
tries of a write the loop had been preempted in.

Priority. With `realtime=True` the loop asks for SCHED_FIFO (Linux, root or CAP_SYS_NICE): the
scheduler then runs it as soon as its tick is due instead of sharing the core in time slices with
whatever else runs. Refused, or not asked, it runs at normal priority (on a loaded machine: late
wake-ups, measured in bench/haptics). It sleeps between ticks (spinning only the last tens of
µs), so it takes a fraction of a core; how it waits, its garbage collector, its memory lock,
timer slack and scheduling slice are `tuning` (tissue.haptics.timing.Tuning). With `cpu=k`
it runs on core k only (os.sched_setaffinity; pin_process puts the simulation on the others):
the two do not take each other's time slices, though other processes still may.

Ending. `stop()` (or leaving the `with` block) sets the stop event and joins; the loop also ends
when its parent process is gone (its parent id changes: checked every tick), and when no problem
has come for `idle_timeout` s. A loop that died is reported by the simulation's next `publish` as
a TissueError. The loop writes its log (every tick: clock, period, force, grip, contact force,
sweeps, residual, step, and where the tick's time went: LOG_COLUMNS; and its CPU and wall
seconds, page faults, context switches) to `log_path` as it ends, however it ends but SIGKILL.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import resource
import time
import zlib
from dataclasses import dataclass
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np

from ..errors import TissueError
from . import timing
from .instrument import DevicePose
from .lcp import MAX_CONTACTS, MAX_JAWS, MAX_SWEEPS, TOLERANCE, HapticProblem

HEADER = 3                     # int64 per slot: sequence, payload length, CRC-32
SLOTS = 2


class TornRead(TissueError):
    """A record whose CRC does not match its payload."""


class SharedRecord:
    """A float64 record in shared memory, two slots under sequence locks (see the module docstring)."""

    def __init__(self, capacity: int, name: str | None = None):
        slot = HEADER + int(capacity)
        if name is None:
            self.shm = shared_memory.SharedMemory(create=True, size=8 * SLOTS * slot)
            self.owner = True
        else:
            # (A spawned child shares its parent's resource tracker: attaching registers the name
            # again in the same set, and the tracker unlinks it if both processes die without.)
            self.shm = shared_memory.SharedMemory(name=name)
            self.owner = False
        self.name = self.shm.name
        slot = self.shm.size // (8 * SLOTS)
        whole = np.ndarray((SLOTS, slot), np.int64, buffer=self.shm.buf)
        self.headers = [whole[k, :HEADER] for k in range(SLOTS)]
        self.payloads = [np.ndarray((slot - HEADER,), np.float64, buffer=self.shm.buf, offset=8 * (k * slot + HEADER))
                         for k in range(SLOTS)]
        if self.owner:
            whole[:, :HEADER] = 0
        self.written, self.retries = 0, 0

    @property
    def sequence(self) -> int:
        """The number of records completely written so far."""
        return max(int(h[0]) for h in self.headers) // 2

    def write(self, data: np.ndarray) -> None:
        """(One writer per record.)"""
        data = np.ascontiguousarray(data, dtype=np.float64).ravel()
        if len(data) > len(self.payloads[0]):
            raise TissueError(f"haptics: a record of {len(data)} values exceeds the channel's {len(self.payloads[0])}")
        self.written += 1
        k = self.written % SLOTS
        h = self.headers[k]
        h[0] = 2 * self.written - 1
        self.payloads[k][:len(data)] = data
        h[1] = len(data)
        h[2] = zlib.crc32(data)
        h[0] = 2 * self.written

    def read(self, attempts: int = 1000):
        """(sequence, a copy of the payload) of the newest complete record; None if none was
        written yet, or if the writer lapped every copy through `attempts` tries (try again later)."""
        for _ in range(attempts):
            # Each header read once: a second read may see the write that began after the first.
            complete = [(s, k) for k, s in enumerate(int(h[0]) for h in self.headers) if s % 2 == 0]
            if not complete:                      # both slots begun between our reads of them
                self.retries += 1
                continue
            s, k = max(complete)
            if s == 0:
                return None
            h = self.headers[k]
            n, crc = int(h[1]), int(h[2])
            data = self.payloads[k][:n].copy()
            if int(h[0]) != s:                    # rewritten while we copied
                self.retries += 1
                continue
            if zlib.crc32(data) != crc:
                raise TornRead(f"haptics: record {s // 2} failed its CRC ({n} values)")
            return s // 2, data
        return None

    def close(self) -> None:
        self.headers = self.payloads = None
        self.shm.close()
        if self.owner:
            self.shm.unlink()


# ---- a HapticProblem as a flat record ----------------------------------------------------------

META = 18                      # step, time, h, n, jaws, device jaw, device position (3), orientation (9)
PER_JAW = 15                   # follow, compliance, stiffness, x (3), target (3), offset (3), axis (3)


def record_size(contacts: int, jaws: int = MAX_JAWS) -> int:
    m = 3 * contacts
    return META + PER_JAW * jaws + m * m + 3 * m + contacts + 3 * m * jaws


def pack(p: HapticProblem) -> np.ndarray:
    meta = np.r_[p.step, p.time, p.h, p.n, p.jaws, p.device_jaw, p.device_position, p.device_orientation.ravel()]
    jaws = np.column_stack([p.follow, p.compliance, p.stiffness, p.x, p.target, p.offset, p.axis]).ravel()
    return np.concatenate([meta, jaws, p.W.ravel(), p.q, p.lam, p.mu, p.J.ravel()])


def unpack(data: np.ndarray) -> HapticProblem:
    n, jaws = int(data[3]), int(data[4])
    m = 3 * n
    J = data[META:META + PER_JAW * jaws].reshape(jaws, PER_JAW)
    o = META + PER_JAW * jaws
    W = data[o:o + m * m].reshape(m, m)
    o += m * m
    q, lam, mu = data[o:o + m], data[o + m:o + 2 * m], data[o + 2 * m:o + 2 * m + n]
    o += 2 * m + n
    return HapticProblem(step=int(data[0]), time=float(data[1]), h=float(data[2]), W=W, q=q, lam=lam, mu=mu,
                         J=data[o:o + 3 * m * jaws].reshape(m, 3 * jaws), follow=J[:, 0], compliance=J[:, 1],
                         stiffness=J[:, 2], x=J[:, 3:6], target=J[:, 6:9], offset=J[:, 9:12], axis=J[:, 12:15],
                         device_position=data[6:9], device_orientation=data[9:18].reshape(3, 3),
                         device_jaw=float(data[5]))


POSE_SIZE = 15                 # time, position (3), orientation (9), jaw, ticks


def pack_pose(pose: DevicePose, ticks: int, out: np.ndarray | None = None) -> np.ndarray:
    """The pose as a record, into `out` if given (the loop reuses one rather than build one each tick)."""
    out = np.empty(POSE_SIZE) if out is None else out
    out[0], out[1:4], out[4:13], out[13], out[14] = pose.time, pose.position, pose.orientation.ravel(), pose.jaw, ticks
    return out


def unpack_pose(data: np.ndarray) -> DevicePose:
    return DevicePose(data[1:4].copy(), data[4:13].reshape(3, 3).copy(), float(data[13]), float(data[0]))


# ---- the loop's process ----------------------------------------------------------------------------

# Per tick: its clock and period (s), what it rendered, and where its time went (µs): late (woke
# after its deadline by), load (a new step's problem: read, unpack, hand-over), device (read the
# pose, write it for the simulation, send the force), solve (the re-solve and its Python), work
# (the tick from wake to sleep) and its thread's CPU time (work - work_cpu: preempted), gc (the
# cyclic collector inside the tick).
LOG_COLUMNS = ("clock", "period", "fx", "fy", "fz", "grip", "cx", "cy", "cz", "sweeps", "residual", "step",
               "solve_us", "x", "y", "z", "late_us", "load_us", "device_us", "work_us", "work_cpu_us", "gc_us")


@dataclass
class _Config:
    """What the haptic process takes from its parent (pickled by `spawn`)."""
    device: object
    rate: float
    max_contacts: int
    max_sweeps: int
    tolerance: float
    problem_channel: str
    pose_channel: str
    parent: int
    idle_timeout: float
    log_path: str
    max_ticks: int
    realtime: bool
    cpu: int | None
    tuning: timing.Tuning


def pin_process(cores) -> set[int]:
    """Run every thread of this process (Taichi's workers included) on `cores` only; returns the
    cores it was allowed before (Linux; elsewhere nothing changes and the set of all is returned).
    (On one core, run numpy with OPENBLAS_NUM_THREADS=1: OpenBLAS's second thread would spin
    against the first on the same core.)"""
    if not hasattr(os, "sched_setaffinity"):
        return set(range(os.cpu_count() or 1))
    before = os.sched_getaffinity(0)
    for task in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(task), set(cores))
        except (ProcessLookupError, PermissionError):      # a thread gone meanwhile
            pass
    return before


class _GcTimer:
    """Seconds Python's cyclic collector ran since the last `take()` (gc.callbacks)."""

    def __init__(self):
        self.total, self.began = 0.0, None
        gc.callbacks.append(self)

    def __call__(self, phase, _info):
        if phase == "start":
            self.began = time.monotonic()
        elif self.began is not None:
            self.total += time.monotonic() - self.began
            self.began = None

    def take(self) -> float:
        spent, self.total = self.total, 0.0
        return spent


def _run(config: _Config, epoch, ready, stop) -> None:
    """The haptic process: see the module docstring."""
    from .. import backend
    from .continuity import ContinuousForce
    from .lcp import HapticSolver

    backend.init("cpu", "f64", cpu_max_num_threads=1)
    solver = ContinuousForce(HapticSolver(config.max_contacts, config.max_sweeps, config.tolerance), config.rate)
    solver.warm()
    problems = SharedRecord(0, name=config.problem_channel)
    poses = SharedRecord(0, name=config.pose_channel)
    device = config.device
    log = np.full((config.max_ticks, len(LOG_COLUMNS)), np.nan)        # (np.full touches every page)
    pose_record = np.zeros(POSE_SIZE)
    ticks, loaded, reason = 0, -1, "stopped"
    settings = timing.apply(config.tuning, config.realtime, config.cpu)
    sleep_until = timing.sleeper(config.tuning)
    gc_timer = _GcTimer()
    clock, thread_time = time.monotonic, time.thread_time
    ready.set()
    cpu, wall = time.process_time(), clock()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    try:
        while epoch.value == 0.0 and not stop.is_set():
            time.sleep(1e-3)
        period = 1.0 / config.rate
        start = epoch.value
        deadline, last_tick = clock(), None
        last_problem = deadline
        while True:
            now = clock()
            if stop.is_set():
                break
            if os.getppid() != config.parent:
                reason = "parent gone"
                break
            work_cpu = thread_time()
            row = log[ticks % config.max_ticks]
            row[0], row[1] = now - start, np.nan if last_tick is None else now - last_tick
            row[16] = 1e6 * (now - deadline)
            if problems.sequence != loaded:
                got = problems.read(attempts=2)     # (lapped by the writer: next tick)
                if got is not None:
                    loaded, data = got
                    solver.load(unpack(data))
                    last_problem = now
            elif now - last_problem > config.idle_timeout:
                reason = "idle"
                break
            t0 = clock()
            row[17] = 1e6 * (t0 - now)
            pose = device.read(row[0])
            poses.write(pack_pose(pose, ticks, pose_record))
            if solver.problem is not None:
                t1 = clock()
                f = solver.solve(pose.position, pose.orientation, pose.jaw)
                t2 = clock()
                row[12] = 1e6 * (t2 - t1)
                device.send(row[0], f.force, f.grip)
                row[2:5], row[5], row[6:9] = f.force, f.grip, f.contact
                row[9], row[10], row[11] = f.sweeps, f.residual, solver.problem.step
                row[13:16] = pose.position
                row[18] = 1e6 * ((t1 - t0) + (clock() - t2))
            else:
                row[18] = 1e6 * (clock() - t0)
            row[21] = 1e6 * gc_timer.take()
            row[20] = 1e6 * (thread_time() - work_cpu)
            row[19] = 1e6 * (clock() - now)
            ticks += 1
            last_tick = now
            deadline += period
            if deadline < clock() - period:     # far behind (a stall): no burst of ticks
                deadline = clock()
            sleep_until(deadline)
    finally:
        after = resource.getrusage(resource.RUSAGE_SELF)
        cycles = gc.collect()                   # what the loop left for the collector (0: nothing leaked)
        kept = log[:min(ticks, config.max_ticks)] if ticks <= config.max_ticks else np.roll(
            log, -(ticks % config.max_ticks), axis=0)
        extra = {}
        if hasattr(device, "forces"):
            extra["device_forces"] = device.forces()
        if config.log_path:
            np.savez(config.log_path, log=kept, columns=np.array(LOG_COLUMNS), ticks=ticks, reason=reason,
                     retries=problems.retries, priority=", ".join(settings),
                     cpu_seconds=time.process_time() - cpu, wall_seconds=clock() - wall,
                     minor_faults=after.ru_minflt - usage.ru_minflt, major_faults=after.ru_majflt - usage.ru_majflt,
                     involuntary_switches=after.ru_nivcsw - usage.ru_nivcsw,
                     voluntary_switches=after.ru_nvcsw - usage.ru_nvcsw, garbage_cycles=cycles, **extra)
        if hasattr(device, "close"):
            device.close()
        problems.close()
        poses.close()


class HapticLoop:
    """The parent's handle on the haptic process (see the module docstring).

        with HapticLoop(ScriptedDevice(trajectory), log_path="haptic.npz") as loop:
            instrument.device = loop.device_pose        # the coupling's target, each step
            while ...:
                loop.wait_for(sim.time + sim.dt)        # real time: step when the clock is there
                sim.step()
                loop.publish(stage)
        loop.log                                        # the loop's ticks (LOG_COLUMNS)
    """

    def __init__(self, device, rate: float = 1000.0, max_contacts: int = MAX_CONTACTS, max_sweeps: int = MAX_SWEEPS,
                 tolerance: float = TOLERANCE, log_path: str | os.PathLike | None = None,
                 idle_timeout: float = 60.0, max_ticks: int = 600_000, realtime: bool = False,
                 cpu: int | None = None, tuning: timing.Tuning | None = None):
        if not (np.isfinite(rate) and 1.0 <= rate <= 20_000.0):
            raise TissueError(f"rate: must be between 1 and 20000 Hz, got {rate!r}")
        if not (idle_timeout > 0):
            raise TissueError(f"idle_timeout: must be > 0 s, got {idle_timeout!r}")
        self.device, self.rate = device, float(rate)
        self.max_contacts, self.max_sweeps, self.tolerance = int(max_contacts), int(max_sweeps), float(tolerance)
        self.log_path = None if log_path is None else str(log_path)
        if cpu is not None and not (isinstance(cpu, int) and 0 <= cpu < (os.cpu_count() or 1)):
            raise TissueError(f"cpu: must be a core number in 0..{(os.cpu_count() or 1) - 1}, got {cpu!r}")
        self.idle_timeout, self.max_ticks, self.realtime = float(idle_timeout), int(max_ticks), bool(realtime)
        self.cpu = cpu
        self.tuning = timing.Tuning() if tuning is None else tuning
        self.process = None
        self.log = None
        self.published = 0

    # ---- life ---------------------------------------------------------------------------------

    def start(self, timeout: float = 300.0) -> "HapticLoop":
        """Start the process, wait until its kernel is ready, then start its clock (now)."""
        ctx = multiprocessing.get_context("spawn")
        self.problems = SharedRecord(record_size(self.max_contacts))
        self.poses = SharedRecord(32)
        self._epoch, self._ready, self._stop = ctx.Value("d", 0.0, lock=False), ctx.Event(), ctx.Event()
        config = _Config(device=self.device, rate=self.rate, max_contacts=self.max_contacts, max_sweeps=self.max_sweeps,
                         tolerance=self.tolerance, problem_channel=self.problems.name, pose_channel=self.poses.name,
                         parent=os.getpid(), idle_timeout=self.idle_timeout, log_path=self.log_path or "",
                         max_ticks=self.max_ticks, realtime=self.realtime, cpu=self.cpu, tuning=self.tuning)
        self.process = ctx.Process(target=_run, args=(config, self._epoch, self._ready, self._stop),
                                   name="tissue-haptics", daemon=True)
        self.process.start()
        deadline = time.monotonic() + timeout
        while not self._ready.wait(0.1):
            if not self.process.is_alive() or time.monotonic() > deadline:
                code = self.process.exitcode
                self._cleanup()
                raise TissueError(f"haptic loop: the process did not start (exit code {code})")
        self._epoch.value = time.monotonic()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """End the loop and collect its log (`self.log`: the rows, `self.log_columns`)."""
        if self.process is None:
            return
        self._stop.set()
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2.0)
        self.exitcode = self.process.exitcode
        self._cleanup()
        if self.log_path and Path(self.log_path).is_file():
            with np.load(self.log_path) as saved:
                self.log = {k: saved[k] for k in saved.files}

    def _cleanup(self) -> None:
        for record in (getattr(self, "problems", None), getattr(self, "poses", None)):
            if record is not None and record.headers is not None:
                record.close()
        self.process = None

    def __enter__(self) -> "HapticLoop":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---- the simulation's side --------------------------------------------------------------------

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    def clock(self) -> float:
        """The loop's clock (s since start), the device's time base."""
        return time.monotonic() - self._epoch.value

    def wait_for(self, clock: float) -> None:
        """Sleep until the loop's clock reaches `clock` (the simulation kept to real time)."""
        left = clock - self.clock()
        if left > 0:
            time.sleep(left)

    def device_pose(self, _time: float | None = None) -> DevicePose:
        """The newest device pose the loop read (an instrument's `device`); the device's own
        pose at time 0 until the first tick."""
        got = self.poses.read()
        if got is None and self.poses.sequence == 0:
            return self.device.read(0.0)
        for _ in range(100):                # (a tick writes 16 values: busy for a microsecond)
            if got is not None:
                return unpack_pose(got[1])
            got = self.poses.read()
        self._alive()                       # a loop that died mid-write: raise; else it is too busy
        raise TissueError("haptic loop: the device's pose stayed busy through 100,000 reads")

    def _alive(self) -> None:
        if self.process is None:
            raise TissueError("haptic loop: not running (start() it first)")
        if not self.process.is_alive():
            code = self.process.exitcode
            self._cleanup()
            raise TissueError(f"haptic loop: the process ended (exit code {code}); the simulation stops")

    def publish(self, stage, step: int | None = None) -> HapticProblem:
        """Hand the loop the contact stage's last problem (see tissue.haptics.lcp.restrict); returns it."""
        from .lcp import restrict

        self._alive()
        self.published += 1
        problem = restrict(stage, self.published if step is None else step, self.max_contacts)
        self.problems.write(pack(problem))
        return problem
