"""The host time of liver_press's Newton solves (solver "auto"'s fallback), this checkout against another commit.

    python -m bench.newton_host [--other c965c67] [--rounds 4] [--steps 45] [--out newton_host]

contact_versus's CPU mean per step carries Newton's cost (a few of liver_press's pressed steps
fall back to it, at several ms each) among every other stage's noise; this measures that cost
alone: subprocesses of each checkout alternate round after round, each running `liver_press`
(compliance warping) for --steps steps and summing the wall time spent in
tissue.contact.newton.solve (host numpy, Gauss-Seidel fallback sweeps included) and its
iterations (equal between two checkouts that compute the same numbers). Per commit: the median
over rounds of the total ms, and this / other. Writes bench/results/newton_host.json (or OUT.json).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

from bench.common import alternate_with_commit, machine, print_machine, write_results

# Runs inside a checkout, over the checkout's own tissue and scenes.
CHILD = r"""
import json, sys, time
from tissue import backend
backend.init("cpu")
from tissue.contact import newton
from tissue.simulation import Simulation
from scenes.liver_press import LiverPress
spent, solves, iterations = 0.0, 0, 0
solve = newton.solve
def timed(*args):
    global spent, solves, iterations
    started = time.perf_counter()
    out = solve(*args)
    spent += time.perf_counter() - started
    solves, iterations = solves + 1, iterations + out[2]
    return out
newton.solve = timed
sim = Simulation(LiverPress().with_overrides(["contact.compliance=warped"]))
for _ in range(int(sys.argv[1])):
    sim.step()
print(json.dumps({"ms": 1e3 * spent, "solves": solves, "iterations": iterations}))
"""


def measure(checkout, steps: int) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(steps)], cwd=checkout, capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(checkout)))
    if done.returncode != 0:
        raise RuntimeError(f"{checkout}: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", default="c965c67", help="the commit to compare with")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=45)
    parser.add_argument("--out", default="newton_host", help="the results' name under bench/results")
    args = parser.parse_args(argv)
    info = machine()
    print_machine(info)
    other, runs = alternate_with_commit(args.other, args.rounds, lambda checkout: measure(checkout, args.steps),
                                        lambda r: f"{r['ms']:.1f} ms in {r['solves']} solves, {r['iterations']} "
                                                  "iterations", "tissue-newton-host-")
    median = {name: statistics.median(r["ms"] for r in rounds) for name, rounds in runs.items()}
    print(f"Newton's host ms over {args.steps} steps, median of {args.rounds} rounds: this {median['this']:.1f}, "
          f"{other} {median['other']:.1f} (this / other {median['this'] / median['other']:.3f})")
    write_results(args.out, {"machine": info, "other_commit": other, "steps": args.steps, "rounds": runs,
                             "median_ms": median, "this_over_other": median["this"] / median["other"]})


if __name__ == "__main__":
    main()
