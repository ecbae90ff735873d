"""Taichi's own IR optimisation passes ("advanced_optimization") against start-up and step time.

    python -m bench.compile_options [--scenes beam liver "liver liver.tets=19000" incline liver_press]
                                    [--settings on off auto] [--steps 30] [--rounds 3] [--clock wall|cpu]

Taichi runs its IR passes (whole-kernel CSE, control-flow optimisation, store forwarding, ...)
before handing a kernel to LLVM, which optimises again. Some of those passes grow faster than
linearly with a kernel's size, and the serial step kernel (a whole implicit step, every CG
iteration and its multigrid V-cycle in one kernel) is large. This measures what the passes cost
and what they buy, per scene, each run a `tissue run NAME --no-render` subprocess:
    cold   empty Taichi cache: wall seconds, CPU seconds of the process, kernel compilation seconds
           (wall and CPU less the mesh's generation, which the first run of a mesh pays)
    warm   the cache filled by that cold run: the median ms per step of each stage (stats.json),
           `rounds` runs per setting, the settings alternated run by run (the machine is shared);
           `--clock cpu` times the stages by the process's CPU time instead of the wall's
The settings: passes on every kernel ("on"), on none ("off"), or per kernel ("auto", the default:
off for the kernels marked `compilation.without_ir_passes`); they reach Taichi through
TISSUE_ADVANCED_OPTIMIZATION (tissue.backend). A cold run also records the CPU seconds of each kernel
function's compilation (the slowest listed). Writes bench/results/compile_options.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, machine, print_machine, write_results

# A scene, optionally with `--set` overrides after it (the large liver steps in parallel).
SCENES = ("beam", "liver", "liver liver.tets=19000", "incline", "liver_press")
SETTINGS = {"on": "1", "off": "0", "auto": "auto"}
# `tissue run` (arguments from argv[3] on) in a process that then writes the compile CPU seconds per
# kernel to the file argv[1] names; argv[2] == "cpu": the stages' times are the process's CPU time.
RUN_AND_REPORT = """
import json, sys, time, types
from tissue import cli, compilation, stats
if sys.argv[2] == "cpu":
    stats.time = types.SimpleNamespace(perf_counter=time.process_time)
code = cli.main(sys.argv[3:])
open(sys.argv[1], "w").write(json.dumps(compilation.seconds_by_kernel(cpu=True)))
sys.exit(code)
"""


def run(scene: str, setting: str, cache: Path, steps: int, arch: str, clock: str) -> dict:
    """One `tissue run` of `scene` (a name and overrides) with the Taichi cache in `cache`: wall,
    CPU and the stats it wrote."""
    name, *overrides = scene.split()
    with tempfile.TemporaryDirectory(prefix="tissue-opt-") as out:
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache), TISSUE_ADVANCED_OPTIMIZATION=SETTINGS[setting])
        sets = [a for o in overrides for a in ("--set", o)]
        by_kernel = Path(out) / "by_kernel.json"
        argv = [sys.executable, "-c", RUN_AND_REPORT, str(by_kernel), clock, "run", name, *sets, "--no-render",
                "--steps", str(steps), "--arch", arch, "--out", out]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if done.returncode != 0:
            raise RuntimeError(f"{scene} ({setting}) failed: {done.stderr.strip()[-2000:]}")
        stats = json.loads((Path(out) / "stats.json").read_text())
        slowest = sorted(json.loads(by_kernel.read_text()).items(), key=lambda kv: -kv[1])[:5]
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    mesh = stats["mesh_generation_seconds"]
    return dict(wall_s=wall - mesh, cpu_s=cpu - mesh, mesh_s=mesh, compile_s=stats["kernel_compilation_seconds"],
                kernels=stats["kernels_compiled"], slowest_kernels_cpu_s={k: round(v, 3) for k, v in slowest},
                ms_per_step=stats["ms_per_step"])


def measure(scene: str, settings: list[str], steps: int, rounds: int, arch: str, clock: str) -> dict:
    with tempfile.TemporaryDirectory(prefix="tissue-opt-cache-") as tmp:
        caches = {s: Path(tmp) / s for s in settings}
        cold = {s: run(scene, s, caches[s], steps, arch, clock) for s in settings}
        warm = {s: [] for s in settings}
        for r in range(rounds):
            for s in settings if r % 2 == 0 else settings[::-1]:
                warm[s].append(run(scene, s, caches[s], steps, arch, clock)["ms_per_step"])
    stages = cold[settings[0]]["ms_per_step"].keys()
    step_ms = {s: {stage: float(np.median([w[stage] for w in warm[s]])) for stage in stages} for s in settings}
    return dict(scene=scene, cold={s: {k: v for k, v in c.items() if k != "ms_per_step"} for s, c in cold.items()},
                ms_per_step=step_ms)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--steps", type=int, default=30, help="steps of each run (default 30)")
    parser.add_argument("--rounds", type=int, default=3, help="warm runs per setting (default 3)")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                        help="the stages' clock in warm runs: wall, or the process's CPU time (all its threads; "
                             "for a loaded machine)")
    parser.add_argument("--out", default="compile_options", help="the JSON's name under bench/results")
    parser.add_argument("--arch", default=os.environ.get("TISSUE_ARCH", "cpu"))
    args = parser.parse_args(argv)

    from tissue import backend

    backend.init(args.arch)
    info = machine()
    print_machine(info)
    rows = []
    for scene in args.scenes:
        row = measure(scene, args.settings, args.steps, args.rounds, args.arch, args.clock)
        rows.append(row)
        for s in args.settings:
            c, ms = row["cold"][s], row["ms_per_step"][s]
            total = ms.get("total", sum(v for k, v in ms.items() if ":" not in k))
            print(f"{scene:<24} passes {s:<4}  cold: wall {c['wall_s']:6.1f} s, CPU {c['cpu_s']:6.1f} s, "
                  f"compile {c['compile_s']:6.1f} s ({c['kernels']} kernels)   warm: {total:7.3f} ms/step "
                  f"({', '.join(f'{k} {v:.3f}' for k, v in ms.items() if ':' not in k)}); slowest to compile (CPU): "
                  f"{', '.join(f'{k} {v:.1f} s' for k, v in c['slowest_kernels_cpu_s'].items())}", flush=True)
    write_results(args.out, dict(machine=info, steps=args.steps, rounds=args.rounds, settings=args.settings,
                                 clock=args.clock, runs=rows))


if __name__ == "__main__":
    main()
