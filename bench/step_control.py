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
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import start_on_cpu, write_results

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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--scenes", nargs="*", default=list(SCENES))
    parser.add_argument("--budget", action="store_true", help="the energy budget off and on, both with the check")
    parser.add_argument("--out", help="the results' name under bench/results (default: step_control_budget with "
                        "--budget, else step_control)")
    args = parser.parse_args(argv)
    info = start_on_cpu()
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
