"""The free motion of `liver_press`'s bodies, this checkout against another commit, from the same state.

    python -m bench.free_motion_versus [--other f7aadf9] [--rounds 3] [--settle 45] [--launches 200]
                                       [--out free_motion_versus]

Two commits whose rounding differs part in `liver_press` (the pressed liver amplifies any change
within the CG tolerance), so whole runs compare the code's cost on different states. Here this
checkout runs the scene for `--settle` steps and keeps each body's state: x, v, the last solve's
dv and CG scalars, and the vectors the warm start keeps (each checkout loads those it has). Then
each checkout, alternately, in a process of its own, builds the scene, and for each body launches its step as the scene takes it (the
serial step with the energy check's two evaluations, one launch) `--launches` times, each from that
state. Per body and commit: the median over rounds of each round's median CPU ms per launch (the
process's CPU time: steadier than the wall clock when other jobs share the cores), the least round,
and the CG iterations; this / other. Writes bench/results/OUT.json.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from bench.common import ROOT, alternate_with_commit, machine, print_machine, run_child, write_results

# The solver's arrays a step reads from its state (those of them a checkout has: "warm", the warm
# start's kept vectors, since tissue.solver.warm_start).
STATE = ("x", "v", "dv", "scalars", "warm")

# Runs in a checkout over its own tissue: with SETTLE, steps the scene and saves its bodies' state
# in STATE_FILE; else loads it and times each body's step from it.
CHILD = r"""
import json, os, sys, time
import numpy as np
from tissue import backend
backend.init("cpu")
from scenes.liver_press import LiverPress
from tissue.solver.state import ITERATION
from tissue.solver.step_control import CHECKED_SERIAL
try:
    from tissue.simulation import Simulation
except ImportError:
    from tissue.scene import Simulation

names, path = os.environ["TISSUE_STATE"].split(), os.environ["TISSUE_STATE_FILE"]
sim = Simulation(LiverPress())
settle, launches = int(os.environ["TISSUE_SETTLE"]), int(os.environ["TISSUE_LAUNCHES"])
if settle:
    for _ in range(settle):
        sim.step()
    np.savez(path, **{f"{body}/{a}": b.solver.arrays[a].to_numpy() for body, b in sim.bodies.items() for a in names
                      if a in b.solver.arrays})
    sys.exit(0)
sim.step()            # compiles
saved = np.load(path)
result = {}
for body, b in sim.bodies.items():
    solver, control = b.solver, b.stepper
    k, o, tol = solver.prepare_step()
    w = control._work_pack()
    cpu = []
    for _ in range(launches):
        for a in names:
            if a in solver.arrays:
                solver.arrays[a].from_numpy(saved[f"{body}/{a}"])
        start = time.process_time()
        CHECKED_SERIAL(k, o, w, tol, control._slot, 0)
        cpu.append(time.process_time() - start)
    result[body] = {"cpu_ms": 1e3 * float(np.median(cpu)),
                    "cg_iterations": int(solver.arrays["scalars"].to_numpy()[ITERATION])}
print("RESULT " + json.dumps(result))
"""


def run(checkout: Path, state_file: Path, settle: int = 0, launches: int = 0) -> dict:
    env = {"TISSUE_STATE": " ".join(STATE), "TISSUE_STATE_FILE": str(state_file), "TISSUE_SETTLE": str(settle),
           "TISSUE_LAUNCHES": str(launches)}
    return run_child(checkout, CHILD, env=env, required=bool(launches))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", default="f7aadf9")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--settle", type=int, default=45, help="steps before the state is kept (45: pressed)")
    parser.add_argument("--launches", type=int, default=200, help="timed launches per body and round")
    parser.add_argument("--out", default="free_motion_versus")
    args = parser.parse_args(argv)

    from tissue import backend

    backend.init("cpu")
    info = machine()
    print_machine(info)
    with tempfile.TemporaryDirectory(prefix="tissue-free-motion-versus-") as tmp:
        state_file = Path(tmp) / "state.npz"
        run(ROOT, state_file, settle=args.settle)
        other, runs = alternate_with_commit(
            args.other, args.rounds, lambda checkout: run(checkout, state_file, launches=args.launches),
            lambda r: "  ".join(f"{body}: {e['cpu_ms']:.3f} ms ({e['cg_iterations']} CG)" for body, e in r.items()),
            "tissue-free-motion-versus-")
    result = {}
    for name in ("this", "other"):
        result[name] = {body: {"cpu_ms": float(np.median([r[body]["cpu_ms"] for r in runs[name]])),
                               "cpu_ms_rounds": [r[body]["cpu_ms"] for r in runs[name]],
                               "cpu_ms_min": float(min(r[body]["cpu_ms"] for r in runs[name])),
                               "cg_iterations": runs[name][0][body]["cg_iterations"]}
                        for body in runs[name][0]}
    bodies = list(result["this"])
    result["this_over_other"] = {body: {"cpu": result["this"][body]["cpu_ms"] / result["other"][body]["cpu_ms"],
                                        "cpu_min": result["this"][body]["cpu_ms_min"]
                                        / result["other"][body]["cpu_ms_min"]} for body in bodies}
    print(f"\n{'body':<10}{'CPU ms, this / ' + other:>28}{'ratio':>8}{'least':>20}{'ratio':>8}{'CG':>8}")
    for body in bodies:
        t, o, q = result["this"][body], result["other"][body], result["this_over_other"][body]
        print(f"{body:<10}{t['cpu_ms']:>18.4f} / {o['cpu_ms']:.4f}{q['cpu']:>8.3f}"
              f"{t['cpu_ms_min']:>11.4f} / {o['cpu_ms_min']:.4f}{q['cpu_min']:>8.3f}"
              f"{t['cg_iterations']:>5} / {o['cg_iterations']}")
    write_results(args.out, dict(machine=info, other_commit=other, rounds=args.rounds, settle=args.settle,
                                 launches=args.launches, **result))


if __name__ == "__main__":
    main()
