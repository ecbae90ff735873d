"""Haptics benchmark (paper §3.6-3.7): the haptic loop's rate and period jitter while the simulation
runs the liver grasp, the time of one haptic re-solve, and the simulation's step time with and
without the loop, in one run on this machine.

For each constraint band (about 50, 150 and 450 rows: the grasp scene with its contact sampling
and alarm distance set to reach them), the scene runs in real time (a step starts when the clock
reaches it; 40 ms steps) alone, with the haptic loop in its own process at 1 kHz (a scripted device
on the scene's path; after each step the simulation publishes the restricted problem) at normal
priority on any core, at normal priority pinned (the loop on core 1, the simulation on core 0),
and pinned at real-time priority (SCHED_FIFO, when allowed), the four alternated ROUNDS times
(this shared machine's load drifts from minute to minute; the 1-minute load average before and
after each run is recorded). In every run the instrument follows the device at the clock (see
run). The loop sleeps to 60 µs before each tick and spins the rest
(tissue.haptics.loop), its per-tick work bounded by the re-solve's sweep cap. Reported: the
loop's achieved rate and its tick periods (median, p99, max) while the simulation ran, the
re-solve's time inside the loop (Python included) and alone on the same problems, the restricted
problems' size, the simulation's step time (median) without and with the loop (pooled, and each
round against the same round's run alone; the simulation on one Taichi thread), wall and CPU (the step's threads: the wall time adds
the time slices other processes take), the publish's own time, and the loop's CPU time. The
150-row band's first pinned normal-priority run gives figures/haptics_force.png: the force the
device renders at the simulation's rate (held) and at the loop's.

    python -m bench.haptics            # all three bands (~7 min on 2 cores)
    python -m bench.haptics --quick    # the 150-row band only
"""

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import FIGURES, machine, print_machine, write_results

BANDS = {   # rows wanted: the grasp scene's contact settings that give about that many
    50: ("contact.sampling=vertices", "contact.distance=0.004"),
    150: ("contact.sampling=edges", "contact.distance=0.004"),
    450: ("contact.sampling=faces", "contact.distance=0.007"),
}
ROUNDS = 2       # runs of each kind per band, alternated (this shared machine's load drifts)
# alone: no haptic loop; normal: the loop at normal priority, both processes on any core; pinned:
# the loop at normal priority on core 1, the simulation on core 0; realtime: pinned, the loop at
# SCHED_FIFO (when allowed).
KINDS = ("alone", "normal", "pinned", "realtime")
LOOP_CORE, SIM_CORES = 1, {0}


def build(overrides):
    from scenes.liver_grasp import LiverGrasp
    from tissue.scene import Simulation

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
    threads), the problems published, the clock at the end and the load averages (1 min) before
    and after."""
    from tissue.haptics.loop import pin_process

    sim, layer = build(overrides)
    instrument = next(iter(layer.instruments.values()))
    load = [os.getloadavg()[0]]
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
            if left > 0:
                time.sleep(left)
            a, cpu = time.perf_counter(), time.process_time()
            sim.step()
            b, cpu = time.perf_counter(), time.process_time() - cpu
            if loop is not None:
                problems.append(loop.publish(layer.stage, k))
            c = time.perf_counter()
            rows = layer.stage.last.rows
            records.append((sim.time, 1e3 * (b - a), 1e3 * (c - b), 0 if rows is None else rows.n_rows,
                            *instrument.coupling_force(), instrument.grip_force(), 1e3 * cpu))
        end = clock()
    finally:
        if loop is not None:
            loop.stop()
        if allowed is not None:
            pin_process(allowed)
    load.append(os.getloadavg()[0])
    return np.array(records), problems, end, load


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


def loop_stats(runs) -> dict:
    """Rate and periods over the runs' ticks while the scene ran ((log, end) per run)."""
    ticks = [log[log[:, 0] <= end] for log, end in runs]
    period = np.concatenate([t[1:, 1][np.isfinite(t[1:, 1])] for t in ticks]) * 1e3
    solving = np.concatenate([t[np.isfinite(t[:, 12])] for t in ticks])
    seconds = sum(end for _, end in runs)
    count = sum(len(t) for t in ticks)
    return {"ticks": int(count), "seconds": float(seconds), "rate_hz": float(count / seconds),
            "period_ms": {"median": float(np.median(period)), "p99": float(np.percentile(period, 99)),
                          "max": float(period.max()), "over_1.2ms_fraction": float(np.mean(period > 1.2)),
                          "over_3ms_count": int(np.sum(period > 3.0))},
            "resolve_us_in_loop": {"median": float(np.median(solving[:, 12])),
                                   "p99": float(np.percentile(solving[:, 12], 99))},
            "sweeps_median": float(np.median(solving[:, 9])), "sweeps_max": int(solving[:, 9].max())}


def band(rows_wanted, overrides, figure=None):
    """The band's runs, alternated ROUNDS times: alone, with the loop at normal priority, with the
    loop at real-time priority."""
    from scenes.liver_grasp import LiverGrasp
    from tissue.haptics.device import ScriptedDevice
    from tissue.haptics.layer import plot_forces
    from tissue.haptics.loop import HapticLoop

    steps = {kind: [] for kind in KINDS}
    loops = {kind: [] for kind in KINDS[1:]}
    notes, loads = {}, {kind: [] for kind in KINDS}
    for round_ in range(ROUNDS):
        for kind in KINDS:
            loop = None
            if kind != "alone":
                tmp = tempfile.TemporaryDirectory()
                loop = HapticLoop(ScriptedDevice(LiverGrasp().grasper.trajectory()), rate=1000.0,
                                  log_path=Path(tmp.name) / "loop.npz", realtime=kind == "realtime",
                                  cpu=LOOP_CORE if kind in ("pinned", "realtime") else None)
            records, problems, end, load = run(overrides, loop, pin=kind in ("pinned", "realtime"))
            steps[kind].append(records)
            loads[kind] += load
            if loop is None:
                continue
            log = loop.log
            tmp.cleanup()
            loops[kind].append((log["log"], end))
            before = notes.get(kind, {})
            cpu = before.get("cpu_seconds", 0.0) + float(log["cpu_seconds"])
            wall = before.get("wall_seconds", 0.0) + float(log["wall_seconds"])
            notes[kind] = {"priority": str(log["priority"]), "exit": str(log["reason"]), "cpu_seconds": cpu,
                           "wall_seconds": wall, "cpu_fraction_of_a_core": cpu / wall,
                           "torn_read_retries": before.get("torn_read_retries", 0) + int(log["retries"])}
            if round_ == 0 and kind == "pinned":
                first = (records, problems, log["log"], end)
    records, problems, ticks, end = first
    pressed = records[:, 3] > 0
    sizes = np.array([p.n for p in problems])
    resolve = resolve_times(problems)
    result = {"rows_wanted": rows_wanted, "settings": list(overrides), "rounds": ROUNDS,
              "rows_median_in_contact": float(np.median(records[pressed, 3])) if pressed.any() else 0.0,
              "rows_max": int(records[:, 3].max()),
              "restricted_contacts_median": float(np.median(sizes[sizes > 0])) if (sizes > 0).any() else 0.0,
              "restricted_contacts_max": int(sizes.max()),
              "resolve_us_alone": {"median": float(np.median(resolve)) if len(resolve) else 0.0,
                                   "p99": float(np.percentile(resolve, 99)) if len(resolve) else 0.0},
              "loops": {kind: {**loop_stats(runs), **notes[kind]} for kind, runs in loops.items()}}
    # Step times: the steps after the first of every run of a kind, pooled; and per round.
    pooled = {kind: np.concatenate([r[1:, 1] for r in runs]) for kind, runs in steps.items()}
    alone_rounds = [np.median(r[1:, 1]) for r in steps["alone"]]
    result["step_ms"] = {kind: {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
                                "per_round_median": [float(np.median(r[1:, 1])) for r in steps[kind]],
                                "ratio_to_alone": float(np.median(v) / np.median(pooled["alone"])),
                                # each round's median against the same round's run alone (minutes apart, not more)
                                "paired_ratios": [float(np.median(r[1:, 1]) / a) for r, a in zip(steps[kind], alone_rounds)]}
                         for kind, v in pooled.items()}
    # The step's CPU time (this process's threads): what the step costs, whoever else runs; the
    # wall time above adds the time slices others take on this shared machine.
    alone_cpu = [np.median(r[1:, 8]) for r in steps["alone"]]
    result["step_cpu_ms"] = {kind: {"median": float(np.median(np.concatenate([r[1:, 8] for r in runs]))),
                                    "paired_ratios": [float(np.median(r[1:, 8]) / a) for r, a in zip(runs, alone_cpu)]}
                             for kind, runs in steps.items()}
    result["load_average_1min"] = {kind: [float(x) for x in v] for kind, v in loads.items()}
    result["publish_ms_median"] = float(np.median(np.concatenate([r[1:, 2] for r in steps["normal"]])))
    if figure is not None:
        ticks = ticks[ticks[:, 0] <= end]
        single = np.c_[records[:, 0], records[:, 4:8], np.zeros((len(records), 3))]
        fast = np.c_[ticks[:, 0], ticks[:, 2:6], ticks[:, 6:9]]
        fast = fast[np.isfinite(fast[:, 1])]
        plot_forces(single, fast, figure, title=f"liver_grasp ({result['rows_median_in_contact']:.0f} rows in "
                                                 "contact): force rendered to the device")
        result["figure"] = str(figure.relative_to(FIGURES.parent))
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the 150-row band only")
    args = parser.parse_args(argv)
    from tissue import backend

    # The simulation on one Taichi thread in every kind: pinned to one core, two threads wait for
    # each other in turns of the scheduler (measured: a 4 s grasp stretched to 13 s at load 9).
    backend.init("cpu", "f64", cpu_max_num_threads=1)
    info = machine()
    print_machine(info)
    # Compile the scene's kernels: the whole grasp once per band's settings (a kernel first needed
    # mid-grasp compiled for 1.5 s inside a timed run: the simulation stalled, the loop rendered a
    # stale problem for a device that moved on).
    for overrides in BANDS.values():
        sim, _ = build(overrides)
        sim.run()
    FIGURES.mkdir(exist_ok=True)
    results = {"machine": info, "bands": []}
    for rows, overrides in BANDS.items():
        if args.quick and rows != 150:
            continue
        r = band(rows, overrides, FIGURES / "haptics_force.png" if rows == 150 else None)
        results["bands"].append(r)
        st = r["step_ms"]
        print(f"~{rows} rows (median {r['rows_median_in_contact']:.0f}, max {r['rows_max']}; restricted "
              f"{r['restricted_contacts_median']:.0f}/{r['restricted_contacts_max']} contacts); re-solve alone "
              f"{r['resolve_us_alone']['median']:.0f} µs (p99 {r['resolve_us_alone']['p99']:.0f}); step alone "
              f"{st['alone']['median']:.2f} ms (rounds {st['alone']['per_round_median']}; CPU "
              f"{r['step_cpu_ms']['alone']['median']:.2f} ms); publish "
              f"{r['publish_ms_median']:.2f} ms")
        for kind, lp in r["loops"].items():
            print(f"    loop {lp['priority']}: {lp['rate_hz']:.0f} Hz, period median {lp['period_ms']['median']:.3f} "
                  f"p99 {lp['period_ms']['p99']:.3f} max {lp['period_ms']['max']:.2f} ms "
                  f"({lp['period_ms']['over_3ms_count']} over 3 ms), "
                  f"{100 * lp['cpu_fraction_of_a_core']:.0f} % of a core; "
                  f"re-solve {lp['resolve_us_in_loop']['median']:.0f} µs "
                  f"(p99 {lp['resolve_us_in_loop']['p99']:.0f}), sweeps {lp['sweeps_median']:.0f}/{lp['sweeps_max']}; "
                  f"step {st[kind]['median']:.2f} ms ({st[kind]['ratio_to_alone']:.2f}×, paired "
                  f"{[round(x, 2) for x in st[kind]['paired_ratios']]}; "
                  f"rounds {st[kind]['per_round_median']}); step CPU {r['step_cpu_ms'][kind]['median']:.2f} ms "
                  f"(paired {[round(x, 2) for x in r['step_cpu_ms'][kind]['paired_ratios']]})")
    write_results("haptics", results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
