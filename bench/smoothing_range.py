"""CG iterations of the multigrid scenes against the range of the multigrid's Chebyshev smoother.

    python -m bench.smoothing_range [--steps 100] [--ranges 30 15 10] [--scenes ...] [--out smoothing_range]

The smoother targets [λ/r, λ] (tissue.solver.multigrid.SMOOTHING_RANGE = r). Its coefficients are
arrays set when a body's multigrid is built, so every range runs in one process, compiled once.
Each scene that uses the multigrid runs `--steps` steps per range; per scene and range: the CG
iterations summed over each body's solves (every solve of a step the energy check halves counted),
the solves, the CPU ms per step (the first range's run includes the compilation: compare the
others), and the largest distance of a body's node from where the first range's run left it. Each
step stops at the scene's ‖r‖ ≤ tol ‖b‖, so the runs differ within that tolerance, step by step;
in a contact scene the difference carries on through the contacts.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import start_on_cpu, write_results

SCENES = ("liver_press", "liver", "beam", "organs", "incline")


def run(name: str, steps: int, smoothing_range: float) -> tuple[dict, dict]:
    """(the row, each body's positions) of `steps` steps of scene `name` at this range."""
    import scenes
    from tissue.simulation import Simulation
    from tissue.solver import multigrid

    multigrid.SMOOTHING_RANGE = smoothing_range
    sim = Simulation(scenes.load(name)())
    start = time.process_time()
    for _ in range(steps):
        sim.step()
    cpu_ms = 1e3 * (time.process_time() - start) / steps
    # every solve's CG iterations, rejected steps' included (ImplicitEuler.record_step counts them)
    solves = {b: body.solver.stats.history.get("cg_iterations", []) for b, body in sim.bodies.items()}
    row = {"scene": name, "range": smoothing_range, "iterations": {b: sum(s) for b, s in solves.items()},
           "solves": {b: len(s) for b, s in solves.items()}, "cpu_ms_per_step": round(cpu_ms, 3)}
    return row, {b: body.solver.positions() for b, body in sim.bodies.items()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--ranges", type=float, nargs="+", default=[30.0, 15.0, 10.0])
    parser.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES))
    parser.add_argument("--out", default="smoothing_range", help="the results' name under bench/results")
    args = parser.parse_args(argv)
    info = start_on_cpu()
    rows = []
    for name in args.scenes:
        first = None
        for smoothing_range in args.ranges:
            row, positions = run(name, args.steps, smoothing_range)
            if first is None:
                first = positions
            row["largest_distance_m"] = {b: float(np.abs(positions[b] - first[b]).max()) for b in positions}
            rows.append(row)
            print(row, flush=True)
    write_results(args.out, {"machine": info, "steps": args.steps, "rows": rows})


if __name__ == "__main__":
    main()
