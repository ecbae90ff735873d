"""Haptics benchmark (paper §3.6-3.7): the haptic loop's rate and period jitter while the simulation
runs the liver grasp, where long periods come from, the time of one haptic re-solve, and the
simulation's step time with and without the loop, in one run on this machine.

For each constraint band (about 50, 150 and 450 rows: the grasp scene with its contact sampling
and alarm distance set to reach them), the scene runs in real time (a step starts when the clock
reaches it; 40 ms steps), in each kind (`kinds`): alone; with the haptic loop in its own process at
1 kHz (a scripted device on the scene's path; after each step the simulation publishes the
restricted problem) at normal priority on any core; alone pinned to core 0; and with the loop
pinned to core 1 at real-time priority (SCHED_FIFO, when allowed), the simulation on core 0. In
every run the instrument follows the device at the clock (see run). The loop's timing settings
are tissue.haptics.timing's defaults; `--tuning` runs instead the ablation of each of them
(`tuning_kinds`, bench/results/haptics_tuning.json).

Reported per kind: the loop's achieved rate and its tick periods (median, p99, p99.9, max, a
histogram) while the simulation ran; the periods over 1.2 and 3 ms by cause (the previous tick's
work ran past the deadline: its load of a new problem, re-solve, device I/O, garbage collection
or preemption; or the loop woke late: the scheduler); the worst ticks' split; the re-solve's time
in the loop (Python included) and alone on the same problems; the loop's CPU share, page faults,
context switches, what a final collection found; the simulation's step time, wall and CPU (the
step's threads: the wall time adds the time slices other processes take), against the simulation
alone pinned as it is; the publish's own time; per run the 1-minute load average before and after
and each core's steal time (a virtual machine: the hypervisor takes a core whatever its priority).
The 150-row band's real-time run gives figures/haptics_force.png: the force the device renders at
the simulation's rate (held) and at the loop's.

    python -m bench.haptics            # all three bands, one run of each kind (3 min at load 4, 4.5 at load 10)
    python -m bench.haptics --quick    # the 450-row band only
    python -m bench.haptics --tuning   # the timing knobs' ablation (~15 min under load 9)
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

# One BLAS thread unless told otherwise (set before numpy loads OpenBLAS; the haptic process
# inherits it): pinned to one core, OpenBLAS's second thread would spin against the first (the
# publish's products). bench/results/haptics_openblas2.json is a run with two.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bench.common import FIGURES, RESULTS, machine, print_machine, write_results  # noqa: E402

BANDS = {   # rows wanted: the grasp scene's contact settings that give about that many
    50: ("contact.sampling=vertices", "contact.distance=0.004"),
    150: ("contact.sampling=edges", "contact.distance=0.004"),
    450: ("contact.sampling=faces", "contact.distance=0.007"),
}
LOOP_CORE, SIM_CORES = 1, {0}
RATE = 1000.0    # Hz, the loop's


def kinds():
    """name -> (loop settings or None for the simulation alone, simulation pinned to SIM_CORES).
    The loop at normal priority, both processes on any core; and the loop pinned to LOOP_CORE at
    real-time priority (SCHED_FIFO, when allowed), the simulation on SIM_CORES; each against the
    simulation alone, pinned or not as it is."""
    return {"alone": (None, False), "normal": ({}, False),
            "alone pinned": (None, True), "realtime pinned": ({"cpu": LOOP_CORE, "realtime": True}, True)}


def tuning_kinds():
    """The ablation of tissue.haptics.timing's knobs: each one changed from the default at normal
    priority, unpinned; 6c0b578's loop (hybrid sleep, 60 µs spin, time.sleep, GC on, nothing locked,
    the default slack and slice) at normal and real-time priority."""
    from tissue.haptics.timing import Tuning

    default = Tuning()
    old = Tuning(absolute=False, collect_garbage=True, lock_memory=False, timer_slack_ns=None, slice_us=None)
    variants = {"default": default, "timing of 6c0b578": old, "GC on": default.changed(collect_garbage=True),
                "memory not locked": default.changed(lock_memory=False),
                "timer slack 50 µs": default.changed(timer_slack_ns=None),
                "time.sleep": default.changed(absolute=False), "no slice": default.changed(slice_us=None),
                "slice 500 µs": default.changed(slice_us=500.0),
                "sleep only": default.changed(sleep="sleep"), "spin only": default.changed(sleep="spin")}
    out = {name: ({"tuning": t}, False) for name, t in variants.items()}
    out["realtime pinned"] = ({"cpu": LOOP_CORE, "realtime": True}, True)
    out["realtime pinned, timing of 6c0b578"] = ({"cpu": LOOP_CORE, "realtime": True, "tuning": old}, True)
    return out


def build(overrides):
    from scenes.liver_grasp import LiverGrasp
    from tissue.simulation import Simulation

    sim = Simulation(LiverGrasp().with_overrides(list(overrides)), arch="cpu", precision="f64")
    sim.stages = [s for s in sim.stages if s.name != "haptics"]      # the loop's process does it here
    layer = next(s for s in sim.stages if s.name == "contact")
    return sim, layer


def run(overrides, loop=None, pin=False):
    """The scene in real time (a HapticLoop, if given, started once the scene is built: its clock
    is the scene's; with `pin`, this process on SIM_CORES while it runs). The instrument follows
    the device at the clock, as a hand would move it: the loop's newest pose, or alone the script
    read at the clock. A simulation that keeps to real time steps the same problems either way;
    where steps overrun 40 ms (450 rows on this loaded machine) it falls behind the device and
    steps other contacts than another run that falls behind by less (a device read at the
    simulation's time instead leaves the loop's forces, at the clock, meaningless). Per step: (time, ms of
    sim.step, ms of publish, rows, force (3), grip, CPU ms of sim.step: all this process's
    threads, ms slept before it), the problems published, the clock at the end and the load averages (1 min) before
    and after."""
    from tissue.haptics.loop import pin_process

    sim, layer = build(overrides)
    instrument = next(iter(layer.instruments.values()))
    load = [os.getloadavg()[0]]
    stolen = steal()
    allowed = pin_process(SIM_CORES) if pin else None
    if loop is not None:
        loop.start()
        instrument.device, clock = loop.device_pose, loop.clock
    else:
        t0 = time.monotonic()
        clock = lambda: time.monotonic() - t0
        script = instrument.device
        instrument.device = lambda _time: script(clock())
    records, problems = [], []
    try:
        for k in range(sim.scene.steps):
            left = sim.time + sim.dt - clock()
            slept = time.perf_counter()
            if left > 0:
                time.sleep(left)
            a, cpu = time.perf_counter(), time.process_time()
            slept = a - slept
            sim.step()
            b, cpu = time.perf_counter(), time.process_time() - cpu
            if loop is not None:
                problems.append(loop.publish(layer.stage, k))
            c = time.perf_counter()
            rows = layer.stage.last.rows
            records.append((sim.time, 1e3 * (b - a), 1e3 * (c - b), 0 if rows is None else rows.n_rows,
                            *instrument.coupling_force(), instrument.grip_force(), 1e3 * cpu, 1e3 * slept))
        end = clock()
    finally:
        if loop is not None:
            loop.stop()
        if allowed is not None:
            pin_process(allowed)
    load.append(os.getloadavg()[0])
    load.append([int(b - a) for a, b in zip(stolen, steal())])
    return np.array(records), problems, end, load


def steal() -> list[int]:
    """Per core, the time the hypervisor ran something else on it (/proc/stat's steal, 10 ms
    units): this machine is a virtual one, and no priority in it keeps its core then."""
    try:
        return [int(line.split()[8]) for line in open("/proc/stat") if line.startswith("cpu") and line[3].isdigit()]
    except (OSError, IndexError, ValueError):
        return []


def resolve_times(problems) -> np.ndarray:
    """µs of one re-solve (device 0.5 mm off the step's pose), in this process, per problem."""
    from tissue.haptics import HapticSolver

    solver = HapticSolver()
    solver.warm()
    out = []
    for p in problems:
        if p.n == 0:
            continue
        solver.load(p)
        samples = []
        for _ in range(5):
            t = time.perf_counter()
            solver.solve(p.device_position + 5e-4, p.device_orientation, p.device_jaw)
            samples.append(time.perf_counter() - t)
        out.append(1e6 * np.median(samples))
    return np.array(out)


COLUMN = {name: i for i, name in enumerate(__import__("tissue.haptics.loop", fromlist=["LOG_COLUMNS"]).LOG_COLUMNS)}
CAUSES = ("woke late", "load", "solve", "device", "gc", "preempted")


def long_periods(log, threshold_ms: float) -> dict:
    """Why periods ran over `threshold_ms`: the previous tick's work ran past this tick's deadline
    (then its largest part: a new problem's load and hand-over, the re-solve, the device's I/O, the
    collector, or the time it was preempted: wall - CPU), or it ended in time and the loop woke
    late (the scheduler)."""
    c = COLUMN
    prev, cur = log[:-1], log[1:]
    long = cur[:, c["period"]] * 1e3 > threshold_ms
    # This tick's deadline as the previous one's plus a period (the loop resets a deadline it is
    # more than a period behind: its own late_us then says nothing of the overrun).
    deadline = prev[:, c["clock"]] - 1e-6 * prev[:, c["late_us"]] + 1.0 / RATE
    overran = prev[:, c["clock"]] + 1e-6 * prev[:, c["work_us"]] > deadline
    parts = np.nan_to_num(np.c_[prev[:, c["load_us"]], prev[:, c["solve_us"]], prev[:, c["device_us"]],
                                prev[:, c["gc_us"]], prev[:, c["work_us"]] - prev[:, c["work_cpu_us"]]])
    cause = np.where(overran, 1 + np.argmax(parts, axis=1), 0)
    return {CAUSES[k]: int(np.sum(long & (cause == k))) for k in range(len(CAUSES))}


def worst_ticks(log, count: int = 5) -> list[dict]:
    """The longest periods with their tick's wake-up and the previous tick's split (µs)."""
    c = COLUMN
    order = np.argsort(-log[1:, c["period"]])[:count] + 1
    return [{"period_ms": float(1e3 * log[i, c["period"]]), "late_us": float(log[i, c["late_us"]]),
             **{f"previous_{k}": float(np.nan_to_num(log[i - 1, c[k]]))
                for k in ("load_us", "solve_us", "device_us", "gc_us", "work_us", "work_cpu_us")}} for i in order]


def loop_stats(runs) -> dict:
    """Rate and periods over the runs' ticks while the scene ran ((log, end, saved) per run)."""
    ticks = [log[log[:, 0] <= end] for log, end, _ in runs]
    period = np.concatenate([t[1:, 1][np.isfinite(t[1:, 1])] for t in ticks]) * 1e3
    solving = np.concatenate([t[np.isfinite(t[:, 12])] for t in ticks])
    work = np.concatenate([t[:, COLUMN["work_us"]] for t in ticks])
    seconds = sum(end for _, end, _ in runs)
    count = sum(len(t) for t in ticks)
    causes = {f"over_{x}ms_by_cause": {k: sum(long_periods(t, x)[k] for t in ticks) for k in CAUSES}
              for x in (1.2, 3)}
    saved = [s for _, _, s in runs]
    total = lambda key: int(sum(int(s[key]) for s in saved))
    return {"ticks": int(count), "seconds": float(seconds), "rate_hz": float(count / seconds),
            "period_ms": {"median": float(np.median(period)), "p99": float(np.percentile(period, 99)),
                          "p999": float(np.percentile(period, 99.9)), "max": float(period.max()),
                          "over_1.2ms_fraction": float(np.mean(period > 1.2)),
                          "over_3ms_count": int(np.sum(period > 3.0)),
                          "histogram_ms": _histogram(period)},
            **causes, "worst": worst_ticks(max(ticks, key=lambda t: np.nanmax(t[1:, 1]) if len(t) > 1 else 0)),
            "work_us": {"median": float(np.median(work)), "p99": float(np.percentile(work, 99))},
            "split_us_median": {k: float(np.nanmedian(np.concatenate([t[:, COLUMN[k]] for t in ticks])))
                                for k in ("late_us", "load_us", "device_us", "solve_us", "work_us", "work_cpu_us")},
            "resolve_us_in_loop": {"median": float(np.median(solving[:, 12])),
                                   "p99": float(np.percentile(solving[:, 12], 99))},
            "sweeps_median": float(np.median(solving[:, 9])), "sweeps_max": int(solving[:, 9].max()),
            "priority": str(saved[0]["priority"]), "exit": sorted({str(s["reason"]) for s in saved}),
            "cpu_fraction_of_a_core": float(sum(float(s["cpu_seconds"]) for s in saved)
                                            / sum(float(s["wall_seconds"]) for s in saved)),
            "minor_faults": total("minor_faults"), "major_faults": total("major_faults"),
            "involuntary_switches": total("involuntary_switches"), "garbage_cycles": total("garbage_cycles"),
            "torn_read_retries": total("retries")}


def _histogram(period_ms) -> dict:
    edges = [0, 0.9, 1.1, 1.2, 1.5, 2, 3, 5, 10, 100, np.inf]
    counts, _ = np.histogram(period_ms, edges)
    return {f"{lo}-{hi}": int(n) for lo, hi, n in zip(edges[:-1], edges[1:], counts)}


def band(rows_wanted, overrides, runs_of, rounds, figure=None):
    """The band's runs of each kind (runs_of: name -> (loop settings, pinned)), alternated `rounds`
    times (this shared machine's load drifts)."""
    from scenes.liver_grasp import LiverGrasp
    from tissue.haptics.device import ScriptedDevice
    from tissue.haptics.layer import plot_forces
    from tissue.haptics.loop import HapticLoop

    steps = {kind: [] for kind in runs_of}
    loops = {kind: [] for kind, (settings, _) in runs_of.items() if settings is not None}
    loads = {kind: [] for kind in runs_of}
    ends = {kind: [] for kind in runs_of}
    first = None
    for round_ in range(rounds):
        for kind, (settings, pin) in runs_of.items():
            loop = None
            if settings is not None:
                tmp = tempfile.TemporaryDirectory()
                loop = HapticLoop(ScriptedDevice(LiverGrasp().grasper.trajectory()), rate=RATE,
                                  log_path=Path(tmp.name) / "loop.npz", **settings)
            records, problems, end, load = run(overrides, loop, pin=pin)
            steps[kind].append(records)
            loads[kind].append({"load_1min": load[:2], "steal_10ms_per_core": load[2]})
            ends[kind].append(end)
            if loop is None:
                continue
            saved = loop.log
            tmp.cleanup()
            loops[kind].append((saved["log"], end, saved))
            if first is None or (round_ == 0 and kind == "realtime pinned"):
                first = (records, problems, saved["log"], end)
            lp = loop_stats(loops[kind][-1:])
            print(f"  {kind:>26} round {round_ + 1}: {lp['rate_hz']:.0f} Hz, p99 {lp['period_ms']['p99']:.3f}, "
                  f"max {lp['period_ms']['max']:.2f} ms, over 1.2 ms {lp['over_1.2ms_by_cause']}, "
                  f"load {load[0]:.1f}-{load[1]:.1f}, steal {load[2]}", flush=True)
    records, problems, ticks, end = first
    pressed = records[:, 3] > 0
    sizes = np.array([p.n for p in problems])
    resolve = resolve_times(problems)
    result = {"rows_wanted": rows_wanted, "settings": list(overrides), "rounds": rounds,
              "rows_median_in_contact": float(np.median(records[pressed, 3])) if pressed.any() else 0.0,
              "rows_max": int(records[:, 3].max()),
              "restricted_contacts_median": float(np.median(sizes[sizes > 0])) if (sizes > 0).any() else 0.0,
              "restricted_contacts_max": int(sizes.max()),
              "resolve_us_alone": {"median": float(np.median(resolve)) if len(resolve) else 0.0,
                                   "p99": float(np.percentile(resolve, 99)) if len(resolve) else 0.0},
              "loops": {kind: loop_stats(runs) for kind, runs in loops.items()}}
    # Step times (wall and this process's CPU), the steps after the first of every run of a kind,
    # against the simulation alone pinned as this kind is (pooled, and each round against the same
    # round's: minutes apart, not more). The CPU time is what the step costs whoever else runs; the
    # wall time adds the time slices others take on this shared machine.
    result["step_ms"] = {}
    for kind, runs in steps.items():
        pin = runs_of[kind][1]
        base = "alone pinned" if pin and "alone pinned" in steps else "alone"
        entry = {"against": base}
        for name, col in (("wall", 1), ("cpu", 8)):
            pooled = np.concatenate([r[1:, col] for r in runs])
            ref = np.concatenate([r[1:, col] for r in steps[base]]) if base in steps else pooled
            entry[name] = {"median": float(np.median(pooled)), "p90": float(np.percentile(pooled, 90)),
                           "ratio": float(np.median(pooled) / np.median(ref)),
                           "paired_ratios": [float(np.median(r[1:, col]) / np.median(a[1:, col]))
                                             for r, a in zip(runs, steps.get(base, runs))]}
        entry["clock_seconds"] = [float(e) for e in ends[kind]]      # of a 4 s grasp kept to real time
        # where each run's clock went: steps, publishes, sleeps to real time, the rest (reading the
        # device's pose, bookkeeping); and its longest step
        entry["clock_split_seconds"] = [{"steps": float(r[:, 1].sum() / 1e3), "steps_cpu": float(r[:, 8].sum() / 1e3),
                                         "publish": float(r[:, 2].sum() / 1e3),
                                         "slept": float(r[:, 9].sum() / 1e3),
                                         "rest": float(e - r[:, [1, 2, 9]].sum() / 1e3), "longest_step_ms": float(r[:, 1].max())}
                                        for r, e in zip(runs, ends[kind])]
        result["step_ms"][kind] = entry
    result["load_and_steal"] = loads         # per run: 1-min load average before and after, steal per core
    publish = [np.concatenate([r[1:, 2] for r in steps[k]]) for k in loops]
    result["publish_ms_median"] = float(np.median(np.concatenate(publish))) if publish else 0.0
    if figure is not None:
        ticks = ticks[ticks[:, 0] <= end]
        single = np.c_[records[:, 0], records[:, 4:8], np.zeros((len(records), 3))]
        fast = np.c_[ticks[:, 0], ticks[:, 2:6], ticks[:, 6:9]]
        fast = fast[np.isfinite(fast[:, 1])]
        plot_forces(single, fast, figure, title=f"liver_grasp ({result['rows_median_in_contact']:.0f} rows in "
                                                 "contact): force rendered to the device")
        result["figure"] = str(figure.relative_to(FIGURES.parent))
    return result


def markdown(results: dict) -> str:
    """The haptics table of docs/performance.md: per band and loop kind, the loop's rate and periods,
    its long periods by cause, its CPU, and the simulation's step against the simulation alone."""
    lines = ["| rows wanted (median in contact) | loop | rate | period p99 / p99.9 / max | ticks; over 1.2 ms: "
             "fraction, woken late, preempted in a tick | loop's CPU, of a core | simulation's step, wall / CPU, "
             "against alone (pinned alike) | grasp took (clock) | load |",
             "|---|---|---|---|---|---|---|---|---|"]
    names = {"normal": "normal priority", "realtime pinned": "SCHED_FIFO, core 1"}
    for band in results["bands"]:
        for kind, loop in band["loops"].items():
            if loop is None:
                continue
            period, causes, step = loop["period_ms"], loop["over_1.2ms_by_cause"], band["step_ms"][kind]
            load = band["load_and_steal"][kind][0]["load_1min"]
            lines.append(
                f"| {band['rows_wanted']} ({band['rows_median_in_contact']:.0f}) | {names.get(kind, kind)} | "
                f"{loop['rate_hz']:,.0f} Hz | {period['p99']:.3f} / {period['p999']:.2f} / {period['max']:.1f} ms | "
                f"{loop['ticks']:,}; {period['over_1.2ms_fraction']:.3f}, {causes['woke late']}, {causes['preempted']} | "
                f"{loop['cpu_fraction_of_a_core']:.2f} | {step['wall']['ratio']:.2f}× / {step['cpu']['ratio']:.2f}× | "
                f"{step['clock_seconds'][0]:.1f} s | {max(load):.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the 450-row band only")
    parser.add_argument("--tuning", action="store_true",
                        help="the ablation of the loop's timing knobs instead (bench/results/haptics_tuning.json)")
    parser.add_argument("--rounds", type=int, default=1, help="runs of each kind per band, alternated")
    parser.add_argument("--bands", type=int, nargs="*", default=list(BANDS), help="rows wanted: 50 150 450")
    parser.add_argument("--out", help="the results' name under bench/results (default haptics, or haptics_tuning)")
    parser.add_argument("--report", action="store_true",
                        help="print docs/performance.md's haptics table from bench/results/haptics.json")
    args = parser.parse_args(argv)
    if args.report:
        print(markdown(json.loads((RESULTS / "haptics.json").read_text())))
        return 0
    from tissue import backend

    # The simulation on one Taichi thread in every kind: pinned to one core, two threads wait for
    # each other in turns of the scheduler (measured: a 4 s grasp stretched to 13 s at load 9).
    backend.init("cpu", "f64", cpu_max_num_threads=1)
    info = machine()
    info["openblas_threads"] = os.environ["OPENBLAS_NUM_THREADS"]
    print_machine(info)
    bands = [450] if args.quick else args.bands
    # Compile the scene's kernels: the whole grasp once per band's settings (a kernel first needed
    # mid-grasp compiled for 1.5 s inside a timed run: the simulation stalled, the loop rendered a
    # stale problem for a device that moved on).
    for rows in bands:
        sim, _ = build(BANDS[rows])
        sim.run()
    FIGURES.mkdir(exist_ok=True)
    runs_of = tuning_kinds() if args.tuning else kinds()
    results = {"machine": info, "kinds": {k: {"pinned": pin, "loop": None if v is None else
                                              {n: str(x) for n, x in v.items()}} for k, (v, pin) in runs_of.items()},
               "bands": []}
    started = time.perf_counter()
    for rows in bands:
        print(f"~{rows} rows", flush=True)
        figure = FIGURES / "haptics_force.png" if rows == 150 and not args.tuning else None
        r = band(rows, BANDS[rows], runs_of, args.rounds, figure)
        results["bands"].append(r)
        st = r["step_ms"]
        print(f"~{rows} rows (median {r['rows_median_in_contact']:.0f}, max {r['rows_max']}; restricted "
              f"{r['restricted_contacts_median']:.0f}/{r['restricted_contacts_max']} contacts); re-solve alone "
              f"{r['resolve_us_alone']['median']:.0f} µs (p99 {r['resolve_us_alone']['p99']:.0f}); publish "
              f"{r['publish_ms_median']:.2f} ms")
        for kind in runs_of:
            lp = r["loops"].get(kind)
            text = f"    {kind:>26}: step {st[kind]['wall']['median']:.2f} ms wall ({st[kind]['wall']['ratio']:.2f}× "
            text += f"{st[kind]['against']}), {st[kind]['cpu']['median']:.2f} ms CPU ({st[kind]['cpu']['ratio']:.2f}×)"
            if lp is not None:
                text += (f"; loop {lp['rate_hz']:.0f} Hz, period median {lp['period_ms']['median']:.3f} "
                         f"p99 {lp['period_ms']['p99']:.3f} max {lp['period_ms']['max']:.2f} ms "
                         f"({lp['period_ms']['over_3ms_count']} over 3 ms), "
                         f"{100 * lp['cpu_fraction_of_a_core']:.0f} % of a core, work {lp['work_us']['median']:.0f} µs")
            print(text)
    results["seconds"] = time.perf_counter() - started
    write_results(args.out or ("haptics_tuning" if args.tuning else "haptics"), results)
    if not args.tuning:
        print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
