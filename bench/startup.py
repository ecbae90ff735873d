"""Start-up cost of `tissue run`: the command's wall time from empty caches and from caches filled by others.

    python -m bench.startup [--scenes incline liver_press liver beam] [--steps 10] [--arch cpu]
    python -m bench.startup --versus COMMIT [--rounds 3] [--scenes ...] [--fill-also ...] [--out NAME]

Each measurement runs `tissue run NAME --no-render --steps N --out TMP` as a subprocess, with the
Taichi offline cache (TI_OFFLINE_CACHE_FILE_PATH) and the mesh cache (TISSUE_CACHE) in folders of
its own:
    cold    both caches empty
    warm    both caches filled first by runs of other scenes and settings: FILLERS and the other
            scenes of --scenes (each with its defaults), less the timed command itself: what a
            user meets on a new scene or a new setting. A contact scene among the others fills the
            contact kernels it shares with the timed one (each filler runs --steps steps too);
            --fill-also adds scenes that fill the caches without being measured themselves
    again   the same command once more: everything cached
    taichi  Taichi's cache empty, the mesh cache holding this scene's meshes (procedural meshes are
            made once per machine): the issue's "from an empty Taichi cache"
Per run: the wall time, and from stats.json the seconds of mesh generation, of kernel compilation
(and the kernels compiled; of it, "machine code": the first launches, where LLVM's JIT generates the
code the offline cache does not keep), of simulation (the run phase without compilation) and the rest (Python
imports, Taichi's start, output).

Also, in this process: a topology edit of a live 3,960-tetrahedron body (remove 10 elements, add
them back: `BodyModel.remove_elements` / `add_elements`, with the solver's assembled blocks
following), its median time over repetitions and the kernels it compiled (none expected).
Writes bench/results/startup.json (or NAME.json with --out NAME).

--versus COMMIT: each scene's cold, warm and again runs, as above, by this checkout and by COMMIT
(a temporary git worktree), alternately for --rounds rounds, each run with caches of its own;
medians of the wall, of the run's CPU seconds (user + system, all threads: what a loaded machine
inflates least) and of its split. Writes bench/results/startup_versus.json (or NAME.json).

--write-bytecode: the runs may write Python's bytecode (`__pycache__`) even where the environment
sets PYTHONDONTWRITEBYTECODE (as these sessions' do), so that, as on a user's machine, only a
checkout's first run compiles tissue's sources to bytecode; without it, every run does (0.1 s).
The JSON records which.
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

from bench.common import ROOT, alternate_with_commit, machine, print_machine, write_results

SCENES = ("incline", "liver_press", "liver", "beam")
FILLERS = (("beam",), ("liver", "--set", "dt=0.03"))


def run(command: tuple[str, ...], caches: Path, steps: int, arch: str, checkout: Path = ROOT,
        taichi_cache: Path | None = None) -> dict:
    """`tissue run` of `command` (scene and options) with the caches under `caches` (Taichi's at
    `taichi_cache` if given); wall, CPU and split."""
    out = caches / "out"
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(taichi_cache or caches / "taichi"),
               TISSUE_CACHE=str(caches / "tissue"), PYTHONPATH=str(checkout))
    argv = [sys.executable, "-m", "tissue", "run", *command, "--no-render", "--steps", str(steps),
            "--arch", arch, "--out", str(out)]
    start, before = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(argv, cwd=checkout, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    stats = json.loads((out / "stats.json").read_text())
    split = dict(wall_s=wall, cpu_s=cpu, mesh_s=stats["mesh_generation_seconds"], compile_s=stats["kernel_compilation_seconds"],
                 machine_code_s=stats["kernel_compilation_machine_code_seconds"], kernels=stats["kernels_compiled"], simulate_s=stats["run_seconds"] - stats["run_compile_seconds"])
    split["other_s"] = wall - split["mesh_s"] - split["compile_s"] - split["simulate_s"]
    return {k: round(v, 3) for k, v in split.items()}


def measure(scene: str, steps: int, arch: str, checkout: Path = ROOT, others: tuple[str, ...] = ()) -> list[dict]:
    """The scene's cold, warm, again and taichi runs (see the docstring); `others`: the other
    scenes whose runs, beside FILLERS, fill the caches for the warm run."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="tissue-startup-") as tmp:
        rows.append(dict(scene=scene, caches="cold", **run((scene,), Path(tmp), steps, arch, checkout)))
    with tempfile.TemporaryDirectory(prefix="tissue-startup-") as tmp:
        fillers = [f for f in dict.fromkeys((*FILLERS, *((s,) for s in others))) if f != (scene,)]
        for filler in fillers:
            run(filler, Path(tmp), steps, arch, checkout)
        rows.append(dict(scene=scene, caches="warm", filled_by=[" ".join(f) for f in fillers],
                         **run((scene,), Path(tmp), steps, arch, checkout)))
        rows.append(dict(scene=scene, caches="again", **run((scene,), Path(tmp), steps, arch, checkout)))
        with tempfile.TemporaryDirectory(prefix="tissue-startup-taichi-") as empty:
            rows.append(dict(scene=scene, caches="taichi",
                             **run((scene,), Path(tmp), steps, arch, checkout, taichi_cache=Path(empty))))
    return rows


def edit_timing(repeats: int = 50) -> dict:
    """Median ms of removing 10 elements from a live 3,960-tet body, and of adding them back."""
    import numpy as np

    from tissue import compilation
    from tissue.fem import CorotationalFEM, Material
    from tissue.mesh import box
    from tissue.solver import ImplicitEuler

    mesh = box(size=(0.11, 0.1, 0.06), cells=(11, 10, 6))
    solver = ImplicitEuler(CorotationalFEM(mesh, Material(3e3, 0.3, 1000.0)), 0.02, gravity=(0.0, 0.0, 0.0))
    solver.step()
    solver.positions()
    model, rng = solver.model, np.random.default_rng(0)
    removing, adding = [], []
    for i in range(repeats + 2):
        if i == 2:              # after the warm-up edits (the edit kernels compile on their first use)
            start = compilation.count()
        ids = rng.choice(model.n_elements, 10, replace=False)
        tets = model.tets[ids].copy()
        t0 = time.perf_counter()
        model.remove_elements(ids)
        t1 = time.perf_counter()
        model.add_elements(tets)
        t2 = time.perf_counter()
        removing.append(t1 - t0)
        adding.append(t2 - t1)
        solver.step()
    return dict(tets=mesh.n_tets, elements_per_edit=10, remove_ms=round(1e3 * float(np.median(removing[2:])), 3),
                add_ms=round(1e3 * float(np.median(adding[2:])), 3), kernels_compiled=compilation.count() - start)


def versus(other: str, scenes: list[str], rounds: int, steps: int, arch: str, info: dict, out: str,
           fill_also: tuple[str, ...] = ()) -> None:
    """Each scene's cold, warm and again runs by this checkout and by `other`, alternately (see the docstring)."""
    import numpy as np

    def measure_all(checkout: Path) -> dict:
        return {scene: {row["caches"]: row for row in measure(scene, steps, arch, checkout, (*scenes, *fill_also))}
                for scene in scenes}

    def describe(rows: dict) -> str:
        return "  ".join(f"{s}: " + "/".join(f"{r['wall_s']:.1f}" for r in runs.values()) for s, runs in rows.items())

    load = os.getloadavg()
    other, runs = alternate_with_commit(other, rounds, measure_all, describe, "tissue-startup-versus-")
    keys = ("wall_s", "cpu_s", "mesh_s", "compile_s", "machine_code_s", "kernels", "simulate_s", "other_s")
    results = {scene: {caches: {name: {key: round(float(np.median([r[scene][caches][key] for r in runs[name]])), 3)
                                       for key in keys} for name in runs}
                       for caches in ("cold", "warm", "again", "taichi")} for scene in scenes}
    print(f"{'scene':<12} {'caches':<6} {'wall s: this':>12} {other:>9} {'CPU s: this':>12} {other:>9}")
    for scene, by_caches in results.items():
        for caches, r in by_caches.items():
            print(f"{scene:<12} {caches:<6} {r['this']['wall_s']:12.1f} {r['other']['wall_s']:9.1f} "
                  f"{r['this']['cpu_s']:12.1f} {r['other']['cpu_s']:9.1f}")
    write_results(out, dict(machine=info, other=other, rounds=rounds, steps=steps, bytecode=_bytecode(),
                                         load_average_before_after=[[round(x, 2) for x in load],
                                                                    [round(x, 2) for x in os.getloadavg()]],
                                         scenes=results, runs=runs))


def _bytecode() -> str:
    """Whether the runs compile tissue's sources to bytecode in each run or read it from __pycache__."""
    return "compiled in every run" if os.environ.get("PYTHONDONTWRITEBYTECODE") else "written once, then read"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--steps", type=int, default=10, help="steps of each run (default 10)")
    parser.add_argument("--arch", default=os.environ.get("TISSUE_ARCH", "cpu"))
    parser.add_argument("--versus", metavar="COMMIT", help="the again runs, alternately with COMMIT's")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of --versus (default 3)")
    parser.add_argument("--fill-also", nargs="+", default=[], metavar="SCENE",
                        help="scenes that also fill the caches before each warm run, unmeasured")
    parser.add_argument("--out", help="the JSON's name under bench/results (default startup, or startup_versus)")
    parser.add_argument("--write-bytecode", action="store_true",
                        help="let the runs write __pycache__ despite PYTHONDONTWRITEBYTECODE (see the docstring)")
    args = parser.parse_args(argv)
    if args.write_bytecode:
        os.environ.pop("PYTHONDONTWRITEBYTECODE", None)      # the runs' environment is this one's

    from tissue import backend

    backend.init(args.arch)
    info = machine()
    print_machine(info)
    if args.versus:
        versus(args.versus, args.scenes, args.rounds, args.steps, args.arch, info, args.out or "startup_versus",
               tuple(args.fill_also))
        return
    print(f"{'scene':<12} {'caches':<6} {'wall s':>7} {'mesh s':>7} {'compile s':>9} {'of it JIT':>9} {'kernels':>7} "
          f"{'simulate s':>10} {'other s':>7}")
    edit = edit_timing()
    print(f"topology edit of {edit['elements_per_edit']} elements on {edit['tets']} tetrahedra: remove "
          f"{edit['remove_ms']:.3f} ms, add {edit['add_ms']:.3f} ms (median), {edit['kernels_compiled']} kernels compiled")
    rows = []
    for scene in args.scenes:
        for row in measure(scene, args.steps, args.arch, others=(*args.scenes, *args.fill_also)):
            rows.append(row)
            print(f"{row['scene']:<12} {row['caches']:<6} {row['wall_s']:7.1f} {row['mesh_s']:7.2f} "
                  f"{row['compile_s']:9.1f} {row['machine_code_s']:9.1f} {row['kernels']:7d} {row['simulate_s']:10.2f} {row['other_s']:7.1f}",
                  flush=True)
    write_results(args.out or "startup", dict(machine=info, steps=args.steps, bytecode=_bytecode(), fillers=[" ".join(f) for f in FILLERS],
                                  runs=rows, topology_edit=edit))


if __name__ == "__main__":
    main()
