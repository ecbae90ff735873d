"""The haptic loop's re-solve (tissue.haptics.lcp.HapticSolver.solve) of this checkout against
another commit's, on the same problems, alternately in one session.

The problems: liver_grasp in the 450-row band of bench/haptics (faces sampled, 7 mm alarm
distance), stepped without the loop, the device at the simulation's time, each step's problem
restricted as the loop receives it. Each commit, in its own process (Taichi on one thread, as the
loop's), loads each problem and re-solves it for 40 ticks (a step's worth at 1 kHz), the device
drifting 0.6 mm over them, each tick from the last one's impulses as the loop does. Per tick: the
thread's CPU µs (this shared machine's other jobs take wall time, not this), the sweeps, and the
jaws' spring forces it renders: the largest difference between the two commits' forces is
reported in N. Per commit: median, p90, p99 and max over the ticks, pooled over rounds and per
round, and the first tick of each problem alone (from the step's λ); the 1-minute load average
before and after.

With --sweeps, this checkout alone for each cap on a tick's sweeps: the CPU µs per tick, and how far
each tick's rendered force is from the converged solution of the tick's problem (the re-solve
continued from where the tick stopped, 1e-11 tolerance), in N: why a tick has as many sweeps as
it has.

    python -m bench.haptic_resolve [--other 52c806e] [--rounds 3] [--out haptic_resolve]
    python -m bench.haptic_resolve --sweeps 10 20 30 60 90 [--out haptic_resolve_sweeps]
"""

import argparse
import json
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bench.common import alternate_with_commit, machine, print_machine, run_child, write_results  # noqa: E402

TICKS = 40                                      # per problem: a 40 ms step at 1 kHz
DRIFT = np.array([5e-4, -2e-4, 3e-4])           # m, the device's motion over a problem's ticks

CHILD = """
import json, os, sys, time
import numpy as np
from tissue import backend
backend.init("cpu", "f64", cpu_max_num_threads=1)
from tissue.haptics.lcp import HapticSolver
from tissue.haptics.loop import unpack
saved = np.load(os.environ["TISSUE_BENCH_PROBLEMS"])
ticks, drift = int(os.environ["TISSUE_BENCH_TICKS"]), np.array(json.loads(os.environ["TISSUE_BENCH_DRIFT"]))
solver = HapticSolver(max_sweeps=int(os.environ["TISSUE_BENCH_SWEEPS"]))
solver.warm()
converged = HapticSolver(max_sweeps=100_000, tolerance=1e-11) if os.environ["TISSUE_BENCH_CONVERGED"] else None
cpu, sweeps, springs, error = [], [], [], []
for name in saved.files:
    p = unpack(saved[name])
    solver.load(p)
    if converged is not None:
        converged.load(p)
    for t in range(ticks):
        position = p.device_position + drift * (t + 1) / ticks
        a = time.thread_time_ns()
        f = solver.solve(position, p.device_orientation, p.device_jaw)
        cpu.append((time.thread_time_ns() - a) / 1e3)
        sweeps.append(f.sweeps)
        springs.append(f.springs.ravel().tolist())
        if converged is not None:
            converged.r[:] = solver.r
            error.append(float(np.abs(converged.solve(position, p.device_orientation, p.device_jaw).springs
                                      - f.springs).max()))
print("RESULT " + json.dumps({"cpu_us": cpu, "sweeps": sweeps, "springs": springs, "error_n": error}))
"""


def problems(path: Path) -> int:
    """Step the 450-row band's grasp and save each step's restricted problem (packed) to `path`."""
    from bench.haptics import BANDS, build
    from tissue.haptics.lcp import restrict
    from tissue.haptics.loop import pack

    sim, layer = build(BANDS[450])
    packed = []
    for k in range(sim.scene.steps):
        sim.step()
        p = restrict(layer.stage, k)
        if p.n:
            packed.append(pack(p))
    np.savez(path, *packed)
    return len(packed)


def measure(checkout: Path, path: Path, sweeps: int = 30, converged: bool = False) -> dict:
    env = {"TISSUE_BENCH_PROBLEMS": str(path), "TISSUE_BENCH_TICKS": str(TICKS),
           "TISSUE_BENCH_DRIFT": json.dumps(DRIFT.tolist()), "TISSUE_BENCH_SWEEPS": str(sweeps),
           "TISSUE_BENCH_CONVERGED": "1" if converged else ""}
    run = run_child(checkout, CHILD, env=env)
    run["load_1min"] = os.getloadavg()[0]
    return run


def stats(us) -> dict:
    us = np.asarray(us)
    return {"median": float(np.median(us)), "p90": float(np.percentile(us, 90)),
            "p99": float(np.percentile(us, 99)), "max": float(us.max())}


def summary(runs: list[dict]) -> dict:
    cpu = np.array([r["cpu_us"] for r in runs])             # (rounds, ticks)
    return {"cpu_us": stats(cpu.ravel()), "cpu_us_first_tick": stats(cpu[:, ::TICKS].ravel()),
            "cpu_us_per_round": [stats(c) for c in cpu], "sweeps_median": float(np.median(runs[0]["sweeps"])),
            "ticks_per_round": int(cpu.shape[1])}


def sweep_caps(args, info, load, path, count) -> None:
    """--sweeps: per cap, CPU µs per tick and the rendered force's distance from the converged one."""
    from bench.common import ROOT

    caps = {}
    for cap in args.sweeps:
        run = measure(ROOT, path, cap, converged=True)
        error = np.array(run["error_n"])
        caps[str(cap)] = {"cpu_us": stats(run["cpu_us"]), "error_n": {"median": float(np.median(error)),
                          "p99": float(np.percentile(error, 99)), "max": float(error.max())},
                          "load_1min": run["load_1min"]}
        print(f"{cap:>4} sweeps: CPU µs median {caps[str(cap)]['cpu_us']['median']:.1f}, "
              f"p99 {caps[str(cap)]['cpu_us']['p99']:.1f}; |F - converged| median {np.median(error):.1e}, "
              f"p99 {np.percentile(error, 99):.1e}, max {error.max():.1e} N", flush=True)
    load.append(os.getloadavg()[0])
    write_results(args.out or "haptic_resolve_sweeps", dict(machine=info, problems=count, ticks_per_problem=TICKS,
                                                            drift_m=DRIFT.tolist(), load_1min=load, caps=caps))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", default="52c806e", help="the commit to compare with (default: 52c806e, the "
                        "re-solve recomputing each contact's row of W every sweep)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--sweeps", type=int, nargs="+", help="this checkout alone with these caps on a tick's sweeps")
    parser.add_argument("--out", help="the results' name under bench/results (default: haptic_resolve, "
                        "haptic_resolve_sweeps with --sweeps)")
    args = parser.parse_args(argv)

    info = machine()
    print_machine(info)
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="tissue-haptic-resolve-") as tmp:
        path = Path(tmp) / "problems.npz"
        count = problems(path)
        if args.sweeps:
            return sweep_caps(args, info, load, path, count)
        other, runs = alternate_with_commit(
            args.other, args.rounds, lambda checkout: measure(checkout, path),
            lambda run: f"CPU µs median {np.median(run['cpu_us']):.1f}, p99 {np.percentile(run['cpu_us'], 99):.1f}",
            "tissue-haptic-resolve-")
    load.append(os.getloadavg()[0])
    result = {name: summary(runs[name]) for name in ("this", "other")}
    springs = {name: np.array(runs[name][0]["springs"]) for name in ("this", "other")}
    result["rendered_force_difference_n"] = float(np.abs(springs["this"] - springs["other"]).max())
    result["rendered_force_largest_n"] = float(np.abs(springs["other"]).max())
    result["this_over_other"] = {k: result["this"]["cpu_us"][k] / result["other"]["cpu_us"][k]
                                 for k in ("median", "p90", "p99")}
    for name, label in (("this", "this"), ("other", other)):
        c, f = result[name]["cpu_us"], result[name]["cpu_us_first_tick"]
        print(f"{label:>8}: CPU µs per tick median {c['median']:.1f}, p90 {c['p90']:.1f}, p99 {c['p99']:.1f}, "
              f"max {c['max']:.0f}; first tick of a problem median {f['median']:.1f}, p99 {f['p99']:.1f}; "
              f"sweeps median {result[name]['sweeps_median']:.0f}")
    print(f"rendered force: largest difference {result['rendered_force_difference_n']:.2e} N "
          f"(of {result['rendered_force_largest_n']:.2f} N); load {load[0]:.2f} -> {load[1]:.2f}")
    write_results(args.out or "haptic_resolve", dict(machine=info, other_commit=other, rounds=args.rounds, problems=count,
                                 ticks_per_problem=TICKS, drift_m=DRIFT.tolist(), load_1min=load, **result))


if __name__ == "__main__":
    main()
