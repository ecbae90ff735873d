"""What the energy check (tissue.solver.step_control, the scenes' default) costs per step: the liver
demo (bench.deformation's meshes and SOFA's settings: dt 0.02 s, E 3000 Pa, ν 0.3, Rayleigh
0.1/0.1, "polar") with the scenes' CG (multigrid to ‖r‖/‖b‖ ≤ 1e-3, at most 100 iterations),
stepped with and without the check alternately, `--rounds` rounds of `steps_for(m)` steps each from
the same hanging start, medians of all samples (warm-up excluded, ti.sync() around each step).
Where no step is rejected (the typical case; `rejections` counts the timed steps') the check costs
its energy evaluation: positions and velocities read back and a signed SVD per element.

    python -m bench.step_control [--rounds 3]
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.common import machine, print_machine, time_steps, write_results
from bench.deformation import make_solver, meshes, steps_for

SCENE_CG = dict(preconditioner="multigrid", tolerance=1e-3, iterations=100)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--arch", default="cpu")
    args = parser.parse_args(argv)
    from tissue import backend
    from tissue.solver.step_control import EnergyControl

    backend.init(arch=args.arch, precision="f64")
    info = machine()
    print_machine(info)
    rows = []
    for label, mesh, fixed, gravity, _ in meshes(quick=True):
        solver = make_solver(mesh, fixed, gravity, rotation="polar", **SCENE_CG)
        control = EnergyControl(solver)
        steppers = {"none": solver.step, "energy": control.step}
        samples = {k: [] for k in steppers}
        for _ in range(args.rounds):
            for kind, step in steppers.items():
                solver.set_state(mesh.points, np.zeros_like(mesh.points))
                solver.stats.history.clear()
                samples[kind].append(time_steps(step, steps_for(mesh.n_tets))["median_ms"])
        rejections = int(sum(solver.stats.history.get("energy_rejections", [])))
        row = {"mesh": label, "tets": mesh.n_tets, "rejections": rejections,
               **{f"{k}_ms": float(np.median(v)) for k, v in samples.items()}}
        row["ratio"] = row["energy_ms"] / row["none_ms"]
        rows.append(row)
        print(f"{label:>18}: unchecked {row['none_ms']:.3f} ms, checked {row['energy_ms']:.3f} ms "
              f"({row['ratio']:.2f}×; {rejections} steps rejected in the last round)", flush=True)
    write_results("step_control", {"machine": info, "rounds": args.rounds, "cg": SCENE_CG, "rows": rows})


if __name__ == "__main__":
    main()
