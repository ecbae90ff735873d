"""The contact step of this checkout against another commit, measured alternately in one session.

    python -m bench.contact_versus [--other 65424df] [--rounds 3] [--out contact_versus] [--scenes liver_floor ...]

This shared machine's speed drifts by tens of percent within an hour, so contact steps of two
commits are compared side by side: subprocesses of each checkout alternate, round after round, each
running this checkout's bench/contact.py (the same scenes and counters for both, over each
checkout's own tissue) with compliance warping: `liver_press` (300-340 rows median while pressed,
steps with ≥ 150 rows), the same at the 4 mm alarm distance (~450 rows, steps with ≥ 420) and SOFA's
floor scene (the 596-tet liver on a rigid floor, μ 0.5, ~36 rows at rest; with the scenes' default
energy step control, the same once settled (steps 400-480: until 4ba5a91 the energy budget
projected nearly every step there; its allowance lets them be), without step control as in SOFA, and with the exact compliance:
CHOLMOD each step, SOFA's sparse LDLᵀ counterpart). Per scene and commit: the median over rounds of each round's median ms
per step, per stage (free motion, detection, constraints, compliance, LCP, correction; the total is
free motion + contact), the process's CPU time per step (all its threads: the work, steadier than
the wall clock when other jobs share the two cores; its median, and its mean, which counts the
few costly steps, such as Newton's fallbacks, that a median hides), Taichi launches per step (replayed ones
included) and numpy arrays handed to kernels per step, and the steps that ended above the solver's
tolerance (1e-6 m); and this / other for the total and the CPU time (median over rounds, and the
least over rounds: the round the machine's other jobs disturbed least; and the mean step's). The other commit is checked
out with `git worktree` into a temporary folder. Writes bench/results/contact_versus.json (or
OUT.json with --out: a comparison with another commit beside it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.common import alternate_with_commit, machine, print_machine, run_child, write_results

# Runs inside a checkout, with this checkout's bench/contact.py (its path in TISSUE_BENCH_CONTACT:
# the same scenes, counters and medians for both commits) over the checkout's own tissue.
CHILD = r"""
import importlib.util, json, os, time
import numpy as np
from tissue import backend
backend.init("cpu")
spec = importlib.util.spec_from_file_location("bench_contact_measuring", os.environ["TISSUE_BENCH_CONTACT"])
bc = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bc)
Simulation = bc.simulation_class()

steps_cpu = []                            # (CPU s of the process, rows) of every step
step = Simulation.step
def timed(self, *args, **kwargs):
    start = time.process_time()
    out = step(self, *args, **kwargs)
    steps_cpu.append((time.process_time() - start, self.stats.counters.get("rows", 0)))
    return out
Simulation.step = timed

def cpu_ms(steps, min_rows, mean=False):
    cpu, rows = np.array(steps_cpu[-steps:]).T
    return 1e3 * float((np.mean if mean else np.median)(cpu[rows >= min_rows]))

def measured(sim, steps, min_rows):
    for _ in range(3):
        sim.step()
    stage = bc.contact_stage(sim)
    start = len(stage.stats.history["rows"])
    with bc.LaunchCounter() as launches:
        out = bc._collect(sim, steps - 3, min_rows=min_rows)
    out.pop("per_step")
    out["cpu_ms_per_step"] = cpu_ms(steps - 3, min_rows)
    out["cpu_ms_per_step_mean"] = cpu_ms(steps - 3, min_rows, mean=True)
    out["launches_per_step"] = sum(launches.counts.values()) / (steps - 3)
    out["numpy_arguments_per_step"] = launches.numpy_arguments / (steps - 3)
    rows = np.array(stage.stats.history["rows"][start:])
    residual = np.array(stage.stats.history["gs_residual"][start:])[rows >= min_rows]
    out["residual_max"], out["steps_above_tolerance"] = float(residual.max()), int(np.sum(residual > 1e-6))
    return out

def settled(sim, steps):
    for _ in range(steps):
        sim.step()
    return sim

runs = {"liver_press": lambda: measured(bc.press("warped"), 80, 150),
        "liver_press_450_rows": lambda: measured(bc.press("warped", [f"contact.distance={bc.WIDE_DISTANCE}"]), 72, 420),
        "liver_floor": lambda: measured(bc.floor_scene("warped"), 80, 30),
        "liver_floor_settled": lambda: measured(settled(bc.floor_scene("warped"), 400), 80, 30),
        "liver_floor_no_step_control": lambda: measured(bc.floor_scene("warped", "none"), 80, 30),
        "liver_floor_exact": lambda: measured(bc.floor_scene("exact"), 80, 30)}
out = {scene: runs[scene]() for scene in os.environ["TISSUE_BENCH_SCENES"].split()}
print("RESULT " + json.dumps(out))
"""
SCENES = ("liver_press", "liver_press_450_rows", "liver_floor", "liver_floor_settled", "liver_floor_no_step_control",
          "liver_floor_exact")
COLUMNS = ("free_motion", "detection", "constraints", "compliance", "lcp", "correction", "contact", "total")


def measure(checkout: Path, scenes=SCENES) -> dict:
    return run_child(checkout, CHILD, env={"TISSUE_BENCH_CONTACT": str(Path(__file__).resolve().with_name("contact.py")),
                                           "TISSUE_BENCH_SCENES": " ".join(scenes)})


def summary(runs: list[dict], scenes=SCENES) -> dict:
    """Per scene: the median over rounds of each column, launches and rows; the worst residual."""
    out = {}
    for scene in scenes:
        r = [run[scene] for run in runs]
        entry = {"ms_per_step": {c: float(np.median([x["ms_per_step"][c] for x in r])) for c in COLUMNS},
                 "cpu_ms_per_step": float(np.median([x["cpu_ms_per_step"] for x in r])),
                 # each round's, and the least: the round least disturbed by the machine's other jobs
                 "cpu_ms_per_step_rounds": [x["cpu_ms_per_step"] for x in r],
                 "cpu_ms_per_step_min": float(min(x["cpu_ms_per_step"] for x in r)),
                 # the mean step (what a user feels: the steps that fall back to Newton count), where measured
                 "cpu_ms_per_step_mean": float(np.median([x.get("cpu_ms_per_step_mean", np.nan) for x in r])),
                 "rows_median": float(np.median([x["rows_median"] for x in r])),
                 "gs_iterations_median": float(np.median([x["gs_iterations_median"] for x in r]))}
        entry["launches_per_step"] = float(np.median([x["launches_per_step"] for x in r]))
        entry["numpy_arguments_per_step"] = float(np.median([x["numpy_arguments_per_step"] for x in r]))
        entry["residual_max"] = float(max(x["residual_max"] for x in r))
        entry["steps_above_tolerance"] = [x["steps_above_tolerance"] for x in r]
        out[scene] = entry
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", default="65424df", help="the commit to compare with (default: 65424df, before "
                        "the contact step's replayed launches)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default="contact_versus", help="the results' name under bench/results")
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES), help="measure only these (default: all)")
    args = parser.parse_args(argv)
    scenes = [scene for scene in SCENES if scene in args.scenes]

    from tissue import backend

    backend.init("cpu")
    info = machine()
    print_machine(info)
    other, runs = alternate_with_commit(
        args.other, args.rounds, lambda checkout: measure(checkout, scenes),
        lambda run: "  ".join(f"{s}: {run[s]['ms_per_step']['total']:.2f} ms" for s in scenes),
        "tissue-contact-versus-")
    result = {"this": summary(runs["this"], scenes), "other": summary(runs["other"], scenes)}
    result["this_over_other"] = {scene: {"total": result["this"][scene]["ms_per_step"]["total"]
                                         / result["other"][scene]["ms_per_step"]["total"],
                                         "cpu": result["this"][scene]["cpu_ms_per_step"]
                                         / result["other"][scene]["cpu_ms_per_step"],
                                         "cpu_min": result["this"][scene]["cpu_ms_per_step_min"]
                                         / result["other"][scene]["cpu_ms_per_step_min"],
                                         "cpu_mean": result["this"][scene]["cpu_ms_per_step_mean"]
                                         / result["other"][scene]["cpu_ms_per_step_mean"]} for scene in scenes}
    for scene in scenes:
        print(f"\n{scene} (rows median {result['this'][scene]['rows_median']:.0f}), ms/step:")
        print(f"{'':<8}" + "".join(f"{c:>13}" for c in COLUMNS) + f"{'CPU ms':>10}{'CPU min':>10}{'CPU mean':>10}"
              f"{'launches':>10}{'numpy args':>11}")
        for name, label in (("this", "this"), ("other", other)):
            e = result[name][scene]
            print(f"{label:<8}" + "".join(f"{e['ms_per_step'][c]:13.2f}" for c in COLUMNS)
                  + f"{e['cpu_ms_per_step']:10.2f}{e['cpu_ms_per_step_min']:10.2f}{e['cpu_ms_per_step_mean']:10.2f}"
                  f"{e['launches_per_step']:10.1f}"
                  f"{e['numpy_arguments_per_step']:11.1f}")
    write_results(args.out, dict(machine=info, other_commit=other, rounds=args.rounds, **result))


if __name__ == "__main__":
    main()
