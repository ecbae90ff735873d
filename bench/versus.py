"""ms per step of this checkout against another commit, measured alternately in one session.

    python -m bench.versus [--other d10f560] [--rounds 3] [--quick] [--preconditioner none] [--rotation large] [--max-tets N]

This machine is shared and its speed drifts by tens of percent within an hour, so two benchmark
runs at different times cannot be compared. Here both commits step the same meshes (those of
bench.deformation: the liver at 596-19,409 tetrahedra and the 220,800-tetrahedron beam; --quick:
the three small livers) in subprocesses that alternate, round after round: per mesh and commit the
median ms per step (warm-up excluded) of each round, then the median over rounds, and the ratio
this / other. The other commit is checked out with `git worktree` into a temporary folder. Both use
bench.deformation's settings (SOFA's liver demo: dt 0.02 s, 25 CG iterations, "large", assembled
CG, execution auto; --preconditioner and --rotation change those two); start-up is bench/startup.py's (here it depends on what each commit's runs
left in Taichi's offline cache). Writes bench/results/versus.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.common import alternate_with_commit, machine, print_machine, run_child, write_results

# Runs inside a checkout: the API used here is common to the commits compared.
CHILD = r"""
import json, sys, time
from tissue import backend
backend.init("cpu")
from bench.common import time_steps
from bench.deformation import make_solver, meshes, steps_for
quick, preconditioner, rotation, max_tets = sys.argv[1] == "quick", sys.argv[2], sys.argv[3], int(sys.argv[4])
rows = []
for label, mesh, fixed, gravity, _ in meshes(quick):
    if mesh.n_tets > max_tets:
        continue
    solver = make_solver(mesh, fixed, gravity, rotation=rotation, preconditioner=preconditioner)
    for _ in range(3):   # warm-up (the kernels' first launches compile) outside both clocks
        solver.step()
    cpu = time.process_time()
    t = time_steps(solver.step, steps_for(mesh.n_tets), warmup=0)
    cpu_ms = 1e3 * (time.process_time() - cpu) / t["samples"]   # all threads
    rows.append(dict(mesh=label, tets=mesh.n_tets, ms=t["median_ms"], cpu_ms=cpu_ms))
print("RESULT " + json.dumps(rows))
"""


def measure(checkout: Path, quick: bool, preconditioner: str = "none", rotation: str = "large",
            max_tets: int = 300_000) -> list[dict]:
    return run_child(checkout, CHILD, ("quick" if quick else "full", preconditioner, rotation, max_tets))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", default="d10f560", help="the commit to compare with (default: d10f560, "
                        "the last before the compile-once engine)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="the three small livers only")
    parser.add_argument("--out", default="versus", help="the JSON's name under bench/results")
    parser.add_argument("--preconditioner", default="none", choices=("none", "jacobi", "multigrid"))
    parser.add_argument("--rotation", default="large", choices=("large", "polar", "invertible", "linear"))
    parser.add_argument("--max-tets", type=int, default=300_000, help="leave out larger meshes (default 300,000)")
    args = parser.parse_args(argv)

    from tissue import backend

    backend.init("cpu")
    info = machine()
    print_machine(info)
    other, runs = alternate_with_commit(
        args.other, args.rounds, lambda checkout: measure(checkout, args.quick, args.preconditioner, args.rotation, args.max_tets),
        lambda run: "  ".join(f"{row['tets']}: {row['ms']:.3f}" for row in run), "tissue-versus-")
    rows = []
    for i, row in enumerate(runs["this"][0]):
        this = float(np.median([run[i]["ms"] for run in runs["this"]]))
        that = float(np.median([run[i]["ms"] for run in runs["other"]]))
        cpu = {name: float(np.median([run[i]["cpu_ms"] for run in runs[name]])) for name in runs}
        rows.append(dict(mesh=row["mesh"], tets=row["tets"], this_ms=round(this, 4), other_ms=round(that, 4),
                         ratio=round(this / that, 3), this_cpu_ms=round(cpu["this"], 4),
                         other_cpu_ms=round(cpu["other"], 4)))
        print(f"{row['mesh']:>22}: this {this:8.3f} ms, {other} {that:8.3f} ms, ratio {this / that:5.2f}"
              f"   CPU ms (mean, all threads, warm-up excluded) {cpu['this']:8.3f} / {cpu['other']:8.3f}")
    write_results(args.out, dict(machine=info, other=other, rounds=args.rounds, quick=args.quick,
                                 preconditioner=args.preconditioner, rotation=args.rotation, meshes=rows))


if __name__ == "__main__":
    main()
