"""Which kernel instances each scene compiles, and which of them the other scenes' runs leave in
Taichi's offline cache.

    python -m bench.cache_misses [--runs liver incline "liver --set dt=0.03" ...] [--steps N] [--out NAME]

Each run (a scene, with settings or not) is `tissue run ... --no-render` (its whole run, or N
steps: some kernels first compile late, at a scene's first contact or cut) with an empty Taichi
offline cache (TI_OFFLINE_CACHE_FILE_PATH) of its own. The cache keeps one file per kernel instance,
named by the instance's key (`T<key>.tic`, a hash of the kernel's IR, its argument layout and the
compile config: what a later process looks up) and holding its LLVM module, which names the kernel.
So run B started with a cache that run A filled compiles exactly B's keys that A's are not:
    misses[B]         B's instances no other run makes (what B compiles after all the others ran)
    pairs[A][B]       B's instances A does not make (B run right after A)
    counts            how many of each
A run whose settings differ from its scene's (`liver --set dt=0.03`) should make no instance of
its own. The meshes are cached once for all runs. Writes bench/results/cache_misses.json (or NAME.json).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import ROOT, machine, print_machine, write_results

RUNS = ("beam", "liver", "organs", "incline", "liver_press", "liver_grasp", "liver_cut", "liver --set dt=0.03",
        "liver_press --set liver.tets=800 --set dt=0.03")
_KERNEL_NAME = re.compile(rb"define void @(\w+?)_c\d+_\d+_kernel_")


def instances(command: str, work: Path, steps: int | None, arch: str) -> dict[str, str]:
    """{instance key: kernel name} that `tissue run COMMAND` puts in an empty offline cache."""
    cache, out = work / "taichi", work / "out"
    shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache), TISSUE_CACHE=str(work.parent / "meshes"),
               PYTHONPATH=str(ROOT))
    argv = [sys.executable, "-m", "tissue", "run", *shlex.split(command), "--no-render", "--arch", arch,
            "--out", str(out), *(("--steps", str(steps)) if steps else ())]
    done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{command} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    found = {}
    for path in cache.rglob("T*.tic"):
        names = {m.group(1).decode() for m in _KERNEL_NAME.finditer(path.read_bytes())}
        found[path.stem] = ",".join(sorted(names)) or "?"
    return found


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", default=list(RUNS), help="scenes, each with its --set options if any")
    parser.add_argument("--steps", type=int, help="steps of each run (default: the scene's whole run)")
    parser.add_argument("--arch", default=os.environ.get("TISSUE_ARCH", "cpu"))
    parser.add_argument("--out", default="cache_misses", help="the JSON's name under bench/results")
    args = parser.parse_args(argv)

    from tissue import backend

    backend.init(args.arch)
    info = machine()
    print_machine(info)
    made = {}
    with tempfile.TemporaryDirectory(prefix="tissue-cache-misses-") as tmp:
        for command in args.runs:
            made[command] = instances(command, Path(tmp) / "run", args.steps, args.arch)
            print(f"{command:<50} {len(made[command]):3d} instances: "
                  f"{', '.join(sorted(made[command].values()))}", flush=True)

    def names(keys, run):
        return sorted(made[run][k] for k in keys)

    misses = {b: names(made[b].keys() - set().union(*(made[a] for a in made if a != b)), b) for b in made}
    pairs = {a: {b: names(made[b].keys() - made[a].keys(), b) for b in made if b != a} for a in made}
    print("\ncompiled after every other run:")
    for run, missed in misses.items():
        print(f"  {run:<50} {len(missed):3d}  {', '.join(missed)}")
    print("\ncompiled right after another run (row: first, column: second; instances):")
    width = max(len(r) for r in made)
    print(" " * width + "".join(f"{i:>4d}" for i in range(len(made))))
    for i, a in enumerate(made):
        print(f"{a:<{width}}" + "".join("   -" if a == b else f"{len(pairs[a][b]):4d}" for b in made) + f"  ({i})")
    write_results(args.out, dict(machine=info, steps=args.steps, load_average=[round(x, 2) for x in os.getloadavg()],
                                 instances={r: sorted(k.values()) for r, k in made.items()},
                                 misses=misses, pairs=pairs, counts=counts(misses, pairs)))


def counts(misses: dict, pairs: dict) -> dict:
    """The numbers of instances of `misses` and `pairs` (what the docs' tables print)."""
    return dict(misses={b: len(names) for b, names in misses.items()},
                pairs={a: {b: len(names) for b, names in row.items()} for a, row in pairs.items()})


if __name__ == "__main__":
    main()
