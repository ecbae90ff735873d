"""What "invertible" costs against "polar": ms per step of the liver demo (SOFA's settings, as
bench.deformation: dt 0.02 s, E 3000 Pa, ν 0.3, Rayleigh 0.1/0.1, CG 25) on the 1,512- and
4,446-tet livers, from two states: as it hangs (no element past the compression limit: the typical
case, where the two differ only by the limit's test) and squashed to a quarter of its height (the
limit active in the first steps; the 3 kPa liver springs back within them, so the timed steps
after the warm-up are mostly the typical case again: `limited_elements` counts the last step's).
The two rotations are stepped alternately, `--rounds` rounds of `steps_for(m)` steps each from the
same state, medians of all samples (warm-up excluded, ti.sync() around each step); beside the wall
time, the process's CPU time per step of each round (its warm-up steps included), the median over
rounds: on a machine shared with other work the CPU time moves less than the wall time.

    python -m bench.rotation_cost [--rounds 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import machine, print_machine, time_steps, write_results
from bench.deformation import make_solver, meshes, steps_for

ROTATIONS = ("polar", "invertible")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--arch", default="cpu")
    args = parser.parse_args(argv)
    from tissue import backend

    backend.init(arch=args.arch, precision="f64")
    info = machine()
    print_machine(info)
    rows = []
    for label, mesh, fixed, gravity, _ in meshes(quick=True)[1:3]:
        for state in ("hanging", "squashed"):
            x = mesh.points.copy()
            if state == "squashed":
                low = x[:, 2].min()
                x[:, 2] = low + 0.25 * (x[:, 2] - low)
            solvers = {r: make_solver(mesh, fixed, gravity, rotation=r) for r in ROTATIONS}
            samples, cpu = {r: [] for r in ROTATIONS}, {r: [] for r in ROTATIONS}
            for _ in range(args.rounds):
                for r, solver in solvers.items():
                    solver.set_state(x, np.zeros_like(x))
                    start = time.process_time()
                    t = time_steps(solver.step, steps_for(mesh.n_tets))
                    cpu[r].append(1e3 * (time.process_time() - start) / (t["samples"] + 3))   # + the warm-up
                    samples[r].append(t["median_ms"])
            limited = solvers["invertible"].fem.work_arrays["limited"].to_numpy()[:mesh.n_tets]
            row = {"mesh": label, "tets": mesh.n_tets, "state": state,
                   "limited_elements": int((np.abs(limited).sum(axis=(1, 2)) > 0).sum()),
                   **{f"{r}_ms": float(np.median(samples[r])) for r in ROTATIONS},
                   **{f"{r}_cpu_ms": float(np.median(cpu[r])) for r in ROTATIONS}}
            row["ratio"] = row["invertible_ms"] / row["polar_ms"]
            row["cpu_ratio"] = row["invertible_cpu_ms"] / row["polar_cpu_ms"]
            rows.append(row)
            print(f"{label:>18} {state:>9}: polar {row['polar_ms']:.3f} ms, invertible {row['invertible_ms']:.3f} ms "
                  f"({row['ratio']:.2f}×); CPU {row['polar_cpu_ms']:.3f} → {row['invertible_cpu_ms']:.3f} ms "
                  f"({row['cpu_ratio']:.2f}×); {row['limited_elements']} elements past the limit at the last step",
                  flush=True)
    write_results("rotation_cost", {"machine": info, "rounds": args.rounds, "rows": rows})


if __name__ == "__main__":
    main()
