"""What each kernel of a scene costs to start: front end, module and machine code, and its size.

    python -m bench.kernel_cost [--scenes incline liver_press] [--steps 10] [--name kernel_cost]

Each scene runs as `tissue run NAME --no-render --steps N` in a child process twice, with the
Taichi offline cache and the mesh cache in a folder of its own: *cold* (caches empty), then
*cached* (the same command again: every module comes from the cache, and what is left is what a
warm start pays in every process). Per kernel instance, in CPU seconds of the process
(`tissue.compilation.instances()`): the front end (Python source to Taichi IR), the module (IR to
LLVM module, or the cache's copy) and the machine code (LLVM's JIT at the first launch); and two
measures of the kernel's size, counted while its front end runs: the `ti.func` call sites inlined
into it (Taichi transforms a ti.func's body again at each one) and the Python AST nodes
transformed; and, from the offline cache the cold run wrote (its modules are LLVM IR text), the
LLVM instructions of the instance's module: what the JIT turns into machine code in every process.
Writes bench/results/NAME.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import ROOT, machine, print_machine, write_results

SCENES = ("incline", "liver_press")
# A function of a cached module: Taichi names it KERNEL_cID_INSTANCE_kernel_TASK_... .
DEFINE = re.compile(r"^define [^@]*@(?P<kernel>.+?)_c\d+_(?P<instance>\d+)_kernel_")


def _describe(value) -> str:
    """A template argument, short: a dataclass by its field values, anything else as is."""
    fields = getattr(value, "__dataclass_fields__", None)
    if fields:
        return "/".join(str(getattr(value, f)) for f in fields)
    return str(value)


def child(scene: str, steps: int, out: Path, result: Path) -> None:
    """In this process: `tissue run`, counting each kernel instance's inlined call sites and AST nodes."""
    from taichi.lang import impl
    from taichi.lang.ast.ast_transformer_utils import Builder
    from taichi.lang.kernel_impl import Func, Kernel
    from taichi.types import template

    from tissue import backend, cli, compilation

    backend.init("cpu")            # installs tissue.compilation's wrappers; the run keeps this init
    counts = {"calls": 0, "nodes": 0}
    func_call, build, materialize = Func.__call__, Builder.__call__, Kernel.materialize

    def counted_call(self, *args, **kwargs):
        if impl.inside_kernel() and not self.is_real_function:
            counts["calls"] += 1
        return func_call(self, *args, **kwargs)

    def counted_build(self, ctx, node):
        counts["nodes"] += 1
        return build(self, ctx, node)

    sizes = []

    def counted_materialize(self, key=None, args=None, arg_features=None):
        before, calls, nodes = len(compilation.instances()), counts["calls"], counts["nodes"]
        materialize(self, key, args, arg_features)
        if len(compilation.instances()) > before:
            templates = [_describe(a) for a, p in zip(args or (), self.arguments) if isinstance(p.annotation, template)]
            sizes.append(dict(variant=" ".join(templates), calls=counts["calls"] - calls,
                              nodes=counts["nodes"] - nodes))

    Func.__call__, Builder.__call__, Kernel.materialize = counted_call, counted_build, counted_materialize
    code = cli.main(["run", scene, "--no-render", "--steps", str(steps), "--arch", "cpu", "--out", str(out)])
    if code:
        raise SystemExit(code)
    rows = [dict(kernel=i.kernel, **size, frontend_s=round(i.frontend_s, 4), module_s=round(i.module_s, 4),
                 machine_code_s=round(i.machine_code_s, 4))
            for i, size in zip(compilation.instances(), sizes)]
    result.write_text(json.dumps(rows))


def llvm_instructions(cache: Path) -> dict[str, list[int]]:
    """Per kernel name, the LLVM instructions of each of its instances' modules (one file each,
    its tasks and the runtime functions they call) in the offline cache `cache` of one process, in
    the order Taichi numbered the instances (its compilation order)."""
    counts: dict[tuple[str, int], int] = {}
    for module in cache.glob("*.tic"):
        lines = module.read_bytes().decode("utf-8", "replace").splitlines()
        names = [match for match in map(DEFINE.match, lines) if match]
        if not names:
            continue
        inside, instructions = False, 0
        for line in lines:
            if line.startswith("define "):
                inside = True
            elif line == "}":
                inside = False
            elif inside and line.startswith("  ") and not line.lstrip().startswith(";"):
                instructions += 1
        counts[names[0]["kernel"], int(names[0]["instance"])] = instructions
    by_kernel: dict[str, list[int]] = {}
    for (kernel, _), count in sorted(counts.items()):
        by_kernel.setdefault(kernel, []).append(count)
    return by_kernel


def with_llvm_instructions(rows: list[dict], by_kernel: dict[str, list[int]]) -> list[dict]:
    """Each row (kernel instances in compilation order) with its module's LLVM instructions (None
    where the cache holds fewer instances of its kernel)."""
    seen: dict[str, int] = {}
    for row in rows:
        i = seen[row["kernel"]] = seen.get(row["kernel"], -1) + 1
        counts = by_kernel.get(row["kernel"], [])
        row["llvm_instructions"] = counts[i] if i < len(counts) else None
    return rows


def run(scene: str, steps: int, caches: Path) -> list[dict]:
    result = caches / "kernels.json"
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(caches / "taichi"), TISSUE_CACHE=str(caches / "tissue"))
    argv = [sys.executable, "-m", "bench.kernel_cost", "--child", scene, "--steps", str(steps),
            "--out", str(caches / "out"), "--result", str(result)]
    done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{scene} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return json.loads(result.read_text())


def print_rows(scene: str, caches: str, rows: list[dict]) -> None:
    print(f"\n{scene}, {caches}: {len(rows)} kernel instances, CPU s: front end "
          f"{sum(r['frontend_s'] for r in rows):.2f}, module {sum(r['module_s'] for r in rows):.2f}, "
          f"machine code {sum(r['machine_code_s'] for r in rows):.2f}; {sum(r['calls'] for r in rows)} call sites, "
          f"{sum(r['nodes'] for r in rows)} AST nodes")
    print(f"{'kernel':<28} {'front end':>9} {'module':>7} {'machine':>7} {'calls':>6} {'nodes':>7} {'LLVM':>7}  variant")
    for r in sorted(rows, key=lambda r: -(r["frontend_s"] + r["machine_code_s"])):
        print(f"{r['kernel']:<28} {r['frontend_s']:9.3f} {r['module_s']:7.3f} {r['machine_code_s']:7.3f} "
              f"{r['calls']:6d} {r['nodes']:7d} {r['llvm_instructions'] or 0:7d}  {r['variant'][:60]}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--name", default="kernel_cost", help="the JSON's name under bench/results")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args.child, args.steps, Path(args.out), Path(args.result))
        return

    from tissue import backend

    backend.init("cpu")
    info = machine()
    print_machine(info)
    load = os.getloadavg()
    results = {}
    for scene in args.scenes:
        with tempfile.TemporaryDirectory(prefix="tissue-kernels-") as tmp:
            results[scene] = {caches: run(scene, args.steps, Path(tmp)) for caches in ("cold", "cached")}
            by_kernel = llvm_instructions(Path(tmp) / "taichi")
            for rows in results[scene].values():
                with_llvm_instructions(rows, by_kernel)
        for caches, rows in results[scene].items():
            print_rows(scene, caches, rows)
    write_results(args.name, dict(machine=info, load_average_before_after=[[round(x, 2) for x in load], [round(x, 2) for x in os.getloadavg()]],
                                  steps=args.steps, scenes=results))


if __name__ == "__main__":
    main()
