"""Whether the contact stage of this checkout computes the same numbers as another commit's, bit for bit.

    python -m bench.contact_same [--other f0c7493] [--cold] [--tolerance T] [--out contact_same]

For changes meant to make the contact stage faster without changing its results (its Python and
numpy glue): both checkouts run the same scenes, by this checkout's bench/contact.py over each
checkout's own tissue, and every step's positions, velocities, contact forces, reactions λ and
sweeps are compared with np.array_equal (a -0.0 equals a 0.0). Scenes: SOFA's floor scene with
compliance warping (60 steps with the scenes' step control, 30 without), with the exact compliance
(20 steps), and `liver_press` (45 steps, its W kept as factors, soft–soft and soft–rigid rows).
Prints the scenes' largest row counts and the differing entries, and where some differ, per scene
and kind of array the largest difference relative to the kind's largest magnitude; exits with 1 if
any differ (with `--tolerance T`: if a relative difference exceeds T or an array changed shape).
`--cold`: this checkout's CG starts from zero (`solver.cg_warm_start=false`), as before the warm
start (a commit before it has no such field). Writes bench/results/contact_same.json (or OUT.json).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import ROOT, alternate_with_commit, machine, print_machine, write_results

SCENES = (("floor", "warped", None, 60), ("floor_no_step_control", "warped", "none", 30),
          ("floor_exact", "exact", None, 20), ("liver_press", "warped", None, 45))

# Runs inside a checkout, with this checkout's bench/contact.py over the checkout's own tissue.
CHILD = r"""
import importlib.util, json, os, sys
import numpy as np
from tissue import backend
backend.init("cpu")
spec = importlib.util.spec_from_file_location("bench_contact_same", os.environ["TISSUE_BENCH_CONTACT"])
bc = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bc)
overrides = json.loads(os.environ["TISSUE_BENCH_OVERRIDES"])
out = {}
for tag, compliance, control, steps in SCENES:
    sim = bc.press(compliance, overrides) if tag == "liver_press" else bc.floor_scene(compliance, control, overrides)
    stage = next(s for s in sim.stages if s.name == "contact").stage
    for i in range(steps):
        sim.step()
        for name, state in sim.state().items():
            out[f"{tag}/{i}/{name}/x"], out[f"{tag}/{i}/{name}/v"] = state["positions"], state["velocities"]
        r = stage.last
        out[f"{tag}/{i}/forces"], out[f"{tag}/{i}/impulses"] = r.contact_forces, r.impulses.copy()
        out[f"{tag}/{i}/sweeps"] = np.array([r.info.iterations if r.info else -1])
np.savez(sys.argv[1], **out)
"""


def run(checkout: Path, folder: Path, overrides: list[str]) -> Path:
    path = folder / f"{checkout.name}.npz"
    env = dict(os.environ, PYTHONPATH=str(checkout), TISSUE_BENCH_OVERRIDES=json.dumps(overrides),
               TISSUE_BENCH_CONTACT=str(Path(__file__).resolve().with_name("contact.py")))
    done = subprocess.run([sys.executable, "-c", f"SCENES = {SCENES!r}\n" + CHILD, str(path)], cwd=checkout,
                          env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{checkout}: {done.stderr.strip()[-2000:]}")
    return path


def compare(this: Path, other: Path) -> dict:
    """The arrays that differ, and per scene and kind of array (x, v, forces, impulses, sweeps) the
    largest difference of the same-shaped ones relative to the largest magnitude of that kind."""
    a, b = np.load(this), np.load(other)
    differ = sorted(set(a.files) ^ set(b.files))
    differ += [k for k in sorted(set(a.files) & set(b.files)) if not np.array_equal(a[k], b[k])]
    rows = {tag: max(len(a[k]) for k in a.files if k.startswith(f"{tag}/") and k.endswith("/impulses"))
            for tag, *_ in SCENES}
    relative = {}
    for tag, *_ in SCENES:
        for kind in ("x", "v", "forces", "impulses", "sweeps"):
            keys = [k for k in a.files if k.startswith(f"{tag}/") and k.endswith(f"/{kind}") and k in b.files]
            same = [k for k in keys if a[k].shape == b[k].shape]
            scale = max((float(np.abs(b[k]).max()) for k in keys if b[k].size), default=0.0)
            largest = max((float(np.abs(a[k] - b[k]).max()) for k in same if a[k].size), default=0.0)
            relative[f"{tag}/{kind}"] = {"relative": largest / scale if scale else largest,
                                         "shapes_differ": len(keys) - len(same)}
    return {"entries": len(a.files), "differ": differ, "rows_max": rows, "largest_difference": relative}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--other", default="f0c7493", help="the commit to compare with")
    parser.add_argument("--cold", action="store_true", help="this checkout's CG started from zero")
    parser.add_argument("--out", default="contact_same", help="the results' name under bench/results")
    parser.add_argument("--tolerance", type=float, default=None,
                        help="for a change that alters rounding: pass (exit 0) when every difference relative to "
                        "its kind's largest magnitude is within it, and no array changed shape")
    args = parser.parse_args(argv)
    cold = ["solver.cg_warm_start=false"] if args.cold else []
    info = machine()
    print_machine(info)
    with tempfile.TemporaryDirectory(prefix="tissue-contact-same-") as tmp:
        folder = Path(tmp)
        other, runs = alternate_with_commit(args.other, 1,
                                            lambda checkout: run(checkout, folder, cold if checkout == ROOT else []),
                                            lambda path: path.name, "tissue-contact-same-")
        result = compare(runs["this"][0], runs["other"][0])
    print(f"largest row counts {result['rows_max']}; {result['entries']} arrays, "
          f"{len(result['differ'])} differ from {other}'s" + (f": {result['differ'][:10]}" if result["differ"] else ""))
    if result["differ"]:
        print("largest difference relative to the largest magnitude (arrays of another shape: rows changed):")
        for key, d in result["largest_difference"].items():
            print(f"  {key:<36} {d['relative']:.2e}" + (f"  ({d['shapes_differ']} of another shape)"
                                                         if d["shapes_differ"] else ""))
    write_results(args.out, {"machine": info, "other": other, "cold": args.cold, "tolerance": args.tolerance,
                             **result})
    within = args.tolerance is not None and all(
        d["relative"] <= args.tolerance and not d["shapes_differ"] for d in result["largest_difference"].values())
    sys.exit(0 if not result["differ"] or within else 1)


if __name__ == "__main__":
    main()
