"""Each scene's solver defaults on the error–time front: every step's CG relative residual
‖r‖/‖b‖ against the time per step, for the scene's defaults and the alternatives they were chosen
from, with the defaults before this choice (commit 038584b: a fixed CG cap, Jacobi) beside them.

A setting *meets* the bar when every step of the scene's full run ends at ‖r‖/‖b‖ ≤ 1e-3
(issue #15); of those the cheapest per step is the default (settings within the machine's noise
of each other: the one that shares its compiled scheme with other scenes). Candidates of a scene run in turn,
`--rounds` times over (this machine is shared: the median over rounds of each run's median ms per
step, the first step left out: it compiles).

    python -m bench.scene_defaults [--rounds 3] [--scenes liver beam]
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.common import machine, print_machine, write_results

BAR = 1e-3
BEFORE = {  # the defaults of commit 038584b, as overrides
    "liver": ["solver.preconditioner=jacobi", "solver.cg_iterations=50", "solver.cg_tolerance=1e-9"],
    "beam": ["solver.preconditioner=jacobi", "solver.cg_iterations=100", "solver.cg_tolerance=1e-9"],
    "organs": ["solver.preconditioner=jacobi", "solver.cg_iterations=50", "solver.cg_tolerance=1e-9"],
    "incline": ["solver.preconditioner=jacobi", "solver.cg_iterations=100", "solver.cg_tolerance=1e-9"],
    "liver_press": ["solver.preconditioner=jacobi", "solver.cg_iterations=50", "solver.cg_tolerance=1e-9"],
}
ALTERNATIVES = {  # stop at the bar itself, capped far above what a step needs
    "jacobi": ["solver.preconditioner=jacobi", "solver.cg_iterations=500", f"solver.cg_tolerance={BAR:g}"],
    "multigrid": ["solver.preconditioner=multigrid", "solver.cg_iterations=100", f"solver.cg_tolerance={BAR:g}"],
}


def _solver(name: str, overrides: list[str]):
    import scenes

    return scenes.load(name)().with_overrides(overrides).solver


def run_once(name: str, overrides: list[str]) -> dict:
    import scenes
    from tissue.options import validate
    from tissue.simulation import Simulation

    scene = validate(scenes.load(name)().with_overrides(overrides))
    sim = Simulation(scene, arch="cpu")
    sim.run()
    history = sim.stats.history
    residual, iterations = np.array(history["cg_residual"]), np.array(history["cg_iterations"])
    ms = sim.ms_per_step(skip=1)
    return dict(ms_per_step=sum(v for k, v in ms.items() if ": " not in k), free_motion_ms=ms["free_motion"],
                residual_max=float(residual.max()), residual_median=float(np.median(residual)),
                steps_above_bar=int((residual > BAR).sum()), steps=len(residual),
                iterations_median=float(np.median(iterations)), iterations_max=int(iterations.max()))


def main() -> None:
    import scenes
    from tissue import backend

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scenes", nargs="*", default=None)
    args = parser.parse_args()
    backend.init("cpu", "f64")
    info = machine()
    print_machine(info)
    results = {}
    for name in args.scenes or scenes.names():
        candidates = {"before (038584b)": BEFORE[name]} if name in BEFORE else {}
        candidates.update(ALTERNATIVES)
        default = next((label for label, overrides in candidates.items()
                        if _solver(name, overrides) == _solver(name, [])), None)
        if default is None:
            candidates["default"] = []
        runs = {label: [] for label in candidates}
        for _ in range(args.rounds):
            for label, overrides in candidates.items():
                runs[label].append(run_once(name, overrides))
        rows = {}
        for label, overrides in candidates.items():
            last = runs[label][-1]
            rows[label] = dict(last, overrides=overrides,
                               ms_per_step=float(np.median([r["ms_per_step"] for r in runs[label]])),
                               free_motion_ms=float(np.median([r["free_motion_ms"] for r in runs[label]])),
                               meets_bar=all(r["steps_above_bar"] == 0 for r in runs[label]))
            r = rows[label]
            print(f"{name:<12} {label:<18} {r['ms_per_step']:8.3f} ms/step (free motion {r['free_motion_ms']:.3f})  "
                  f"residual max {r['residual_max']:.1e}  iterations {r['iterations_median']:.0f}/{r['iterations_max']}  "
                  f"{'meets' if r['meets_bar'] else 'misses'} ≤{BAR:g} ({r['steps_above_bar']}/{r['steps']} above)",
                  flush=True)
        meeting = [label for label in rows if rows[label]["meets_bar"]]
        cheapest = min(meeting, key=lambda label: rows[label]["ms_per_step"]) if meeting else None
        default = default or "default"
        print(f"{name:<12} cheapest meeting the bar: {cheapest}; the scene's default is {default} and "
              f"{'meets' if rows[default]['meets_bar'] else 'MISSES'} it", flush=True)
        results[name] = dict(candidates=rows, cheapest=cheapest, default=default)
    write_results("scene_defaults", dict(machine=info, bar=BAR, rounds=args.rounds, scenes=results))


if __name__ == "__main__":
    main()
