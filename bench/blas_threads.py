"""The dense set-up of a contact scene on one BLAS thread against OpenBLAS's default, side by side.

    python -m bench.blas_threads [--rounds 3] [--repeats 3] [--out blas_threads]

`tissue run` sets OPENBLAS_NUM_THREADS=1 unless it is set (tissue/cli.py). This measures why: the
rest compliance A₀⁻¹ of a box body (`solver.reference.rest_compliance`, LAPACK potrf/potri, what
`incline` and `liver_press` compute for each body before their first step) at three sizes, in
child processes that alternate between OPENBLAS_NUM_THREADS=1 and the variable unset (OpenBLAS
then uses a thread per core), round after round. Per size and setting: every call's wall and
process CPU milliseconds, and their medians over rounds and repeats. The machine is shared: the
load average at the start and the end is recorded. Writes bench/results/NAME.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from bench.common import ROOT, machine, print_machine, write_results

CELLS = ((4, 4, 2), (8, 8, 4), (12, 12, 6))      # 225, 1,215 and 3,549 dofs
CHILD = r"""
import json, sys, time
from tissue.fem import Material
from tissue.mesh import box
from tissue.solver.reference import rest_compliance
cells, repeats = json.loads(sys.argv[1]), int(sys.argv[2])
rows = []
for c in cells:
    mesh = box(cells=tuple(c))
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        rest_compliance(mesh, Material(5e4, 0.3, 1000.0), 0.01)
        rows.append(dict(dofs=3 * mesh.n_points, wall_ms=1e3 * (time.perf_counter() - wall),
                         cpu_ms=1e3 * (time.process_time() - cpu)))
print("ROWS", json.dumps(rows))
"""


def child(threads: str | None, repeats: int) -> list[dict]:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if threads is not None:
        env["OPENBLAS_NUM_THREADS"] = threads
    env["PYTHONPATH"] = str(ROOT)
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(CELLS), str(repeats)], cwd=ROOT, env=env,
                          capture_output=True, text=True, check=True)
    line = next(line for line in done.stdout.splitlines() if line.startswith("ROWS "))
    return json.loads(line[5:])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="calls per size in each child (default 3)")
    parser.add_argument("--out", default="blas_threads", help="the JSON's name under bench/results")
    args = parser.parse_args(argv)

    from tissue import backend

    backend.init("cpu")
    info = machine()
    print_machine(info)
    load = os.getloadavg()
    settings = {"one": "1", "default": None}
    runs = {name: [] for name in settings}
    for r in range(args.rounds):
        for name in (settings if r % 2 == 0 else reversed(list(settings))):
            runs[name].extend(child(settings[name], args.repeats))
    print(f"{'dofs':>6} {'wall ms: one':>13} {'default':>9} {'CPU ms: one':>12} {'default':>9}   (medians)")
    sizes = sorted({row["dofs"] for row in runs["one"]})
    medians = {}
    for dofs in sizes:
        medians[dofs] = {name: {key: round(float(np.median([row[key] for row in rows if row["dofs"] == dofs])), 1)
                                for key in ("wall_ms", "cpu_ms")} for name, rows in runs.items()}
        m = medians[dofs]
        print(f"{dofs:6d} {m['one']['wall_ms']:13.1f} {m['default']['wall_ms']:9.1f} "
              f"{m['one']['cpu_ms']:12.1f} {m['default']['cpu_ms']:9.1f}")
    write_results(args.out, dict(machine=info, rounds=args.rounds, repeats=args.repeats, cores=os.cpu_count(),
                                 load_average_before_after=[[round(x, 2) for x in load],
                                                            [round(x, 2) for x in os.getloadavg()]],
                                 medians={str(d): m for d, m in medians.items()},
                                 runs={name: [{k: round(v, 1) if isinstance(v, float) else v for k, v in row.items()}
                                              for row in rows] for name, rows in runs.items()}))


if __name__ == "__main__":
    main()
