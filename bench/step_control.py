"""What the energy check (tissue.solver.step_control, the scenes' default `solver.step_control=energy`)
costs per step on the scenes `beam`, `liver` and `liver_press`: each scene built twice, with the
check and without it (`solver.step_control=none`), the two stepped alternately, `--steps` steps each
per round for `--rounds` rounds, continuing their runs (which goes first alternates between rounds;
the first step of each, which compiles, is left out). Per setting: the median wall ms of the whole
step (every stage, ti.sync() at each stage's end) and of the free motion (where the check runs),
the process's CPU ms per step (its blocks of steps, median; on this shared machine the steadier
figure), and the steps the check rejected (each redone as two half steps). Where it rejects none
(the typical case) the check costs its energy evaluations: a signed principal-stretch eigensolve per
element at a step's end (its start reuses it unless contact moved the state; then, where the solver
runs serially, it is computed from the step's own rotations), in the step's launch where the
solver runs serially, a launch of its own at each otherwise.

    python -m bench.step_control [--rounds 5] [--steps 10] [--scenes beam liver liver_press]
    python -m bench.step_control --budget     # the energy budget's cost on top of the check
                                              # (tissue.solver.energy_budget): step_control_budget.json,
                                              # "none" the budget off, "energy" on (both checked)
    python -m bench.step_control --budget --out NAME     # the same into bench/results/NAME.json
    python -m bench.step_control --versus COMMIT [--rounds 3] [--scenes organs] [--out NAME]

--versus COMMIT: each scene's whole run as `tissue run` steps it (the scene's settings, its
duration's steps), by this checkout and by COMMIT (a temporary git worktree), in subprocesses
alternately for --rounds rounds: the CPU ms of all its steps after the first (which compiles)
over their number, where a rejected step's redoing counts (the median above leaves it out), the
rejections, and whether the two runs end in the same state bit for bit.
Writes bench/results/step_control_versus.json (or NAME.json).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from bench.common import alternate_with_commit, run_child, start_on_cpu, write_results

SCENES = ("beam", "liver", "liver_press")
SETTINGS = {"none": ["solver.step_control=none"], "energy": ["solver.step_control=energy", "solver.energy_budget=false"]}
BUDGET = {"none": ["solver.energy_budget=false"], "energy": ["solver.energy_budget=true"]}   # both checked


def build(name: str, overrides: list[str]):
    import scenes
    from tissue.options import validate
    from tissue.simulation import Simulation

    return Simulation(validate(scenes.load(name)().with_overrides(overrides)), arch="cpu")


def measure(name: str, rounds: int, steps: int, settings: dict = SETTINGS) -> dict:
    sims = {k: build(name, overrides) for k, overrides in settings.items()}
    for sim in sims.values():
        sim.step()                                   # compiles: left out below
    cpu = {k: [] for k in sims}
    for r in range(rounds):
        for k in (list(sims) if r % 2 == 0 else list(sims)[::-1]):
            start = time.process_time()
            for _ in range(steps):
                sims[k].step()
            cpu[k].append(1e3 * (time.process_time() - start) / steps)
    row = {"scene": name, "steps": rounds * steps}
    for k, sim in sims.items():
        times = {s: 1e3 * np.array(t[1:]) for s, t in sim.stats.times.items() if ": " not in s}
        row[k] = {"ms_per_step": float(np.median(sum(times.values()))),
                  "free_motion_ms": float(np.median(times["free_motion"])),
                  "cpu_ms_per_step": float(np.median(cpu[k])),
                  "rejections": int(np.sum(sim.stats.history.get("energy_rejections", []))),
                  "budget_projections": int(np.sum(sim.stats.history.get("budget_projections", [])))}
    row["ratio_wall"] = row["energy"]["ms_per_step"] / row["none"]["ms_per_step"]
    row["ratio_cpu"] = row["energy"]["cpu_ms_per_step"] / row["none"]["cpu_ms_per_step"]
    return row


# Runs inside a checkout: the API used here is common to the commits compared.
CHILD = r"""
import hashlib, json, sys, time
import numpy as np
import scenes
from tissue.options import validate
from tissue.simulation import Simulation
sim = Simulation(validate(scenes.load(sys.argv[1])()), arch="cpu")
steps = round(sim.scene.duration / sim.scene.dt)
sim.step()
started = time.process_time()
for _ in range(steps - 1):
    sim.step()
cpu_ms = 1e3 * (time.process_time() - started) / (steps - 1)
state = hashlib.sha256()
for body in sim.state().values():
    for array in body.values():
        state.update(np.ascontiguousarray(array).tobytes())
rejections = int(np.sum(sim.stats.history.get("energy_rejections", [])))
print("RESULT " + json.dumps(dict(steps=steps, cpu_ms_per_step=cpu_ms, rejections=rejections,
                                  state=state.hexdigest())))
"""


def run_in(checkout: Path, scene: str) -> dict:
    return run_child(checkout, CHILD, (scene,))


def versus(other: str, scenes: list[str], rounds: int, info: dict, out: str) -> None:
    def measure_all(checkout: Path) -> dict:
        return {name: run_in(checkout, name) for name in scenes}

    def describe(rows: dict) -> str:
        return "  ".join(f"{name} {r['cpu_ms_per_step']:.2f} ms ({r['rejections']} rejected)"
                         for name, r in rows.items())

    load_before = os.getloadavg()
    other, runs = alternate_with_commit(other, rounds, measure_all, describe, "step_control_versus_")
    rows = {}
    for name in scenes:
        row = {side: {"cpu_ms_per_step": float(np.median([r[name]["cpu_ms_per_step"] for r in runs[side]])),
                      "rejections": runs[side][0][name]["rejections"]} for side in runs}
        row["ratio_cpu"] = row["this"]["cpu_ms_per_step"] / row["other"]["cpu_ms_per_step"]
        row["same_state"] = len({r[name]["state"] for side in runs for r in runs[side]}) == 1
        row["steps"] = runs["this"][0][name]["steps"]
        rows[name] = row
        print(f"{name:>12}: CPU {row['this']['cpu_ms_per_step']:.2f} ms a step against {other}'s "
              f"{row['other']['cpu_ms_per_step']:.2f} ({row['ratio_cpu']:.2f}×), "
              f"rejections {row['this']['rejections']} "
              f"and {row['other']['rejections']}, same state: {row['same_state']}")
    write_results(out, {"machine": info, "other": other, "rounds": rounds,
                        "load_average_before_after": [load_before[0], os.getloadavg()[0]], "rows": rows, "runs": runs})


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--scenes", nargs="*", default=list(SCENES))
    parser.add_argument("--budget", action="store_true", help="the energy budget off and on, both with the check")
    parser.add_argument("--versus", metavar="COMMIT", help="whole runs of the scenes, alternately with COMMIT's")
    parser.add_argument("--out", help="the results' name under bench/results (default: step_control_budget with "
                        "--budget, step_control_versus with --versus, else step_control)")
    args = parser.parse_args(argv)
    info = start_on_cpu()
    if args.versus:
        versus(args.versus, args.scenes, args.rounds, info, args.out or "step_control_versus")
        return
    rows = []
    for name in args.scenes:
        row = measure(name, args.rounds, args.steps, BUDGET if args.budget else SETTINGS)
        rows.append(row)
        none, energy = row["none"], row["energy"]
        print(f"{name:>12}: step {none['ms_per_step']:.2f} → {energy['ms_per_step']:.2f} ms wall ({row['ratio_wall']:.2f}×; "
              f"free motion {none['free_motion_ms']:.2f} → {energy['free_motion_ms']:.2f}), CPU {none['cpu_ms_per_step']:.2f} → "
              f"{energy['cpu_ms_per_step']:.2f} ms ({row['ratio_cpu']:.2f}×); {energy['rejections']} of {row['steps']} "
              f"steps rejected, {energy['budget_projections']} projected by the budget", flush=True)
    write_results(args.out or ("step_control_budget" if args.budget else "step_control"),
                  {"machine": info, "settings": BUDGET if args.budget else SETTINGS, "rounds": args.rounds,
                   "steps_per_round": args.steps, "rows": rows})


if __name__ == "__main__":
    main()
