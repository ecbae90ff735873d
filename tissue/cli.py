"""The `tissue` command.

    tissue run NAME [--steps N] [--set a.b=v ...] [--out DIR] [--arch A] [--precision P] [--no-render]
    tissue list                 the scenes, with what each shows
    tissue show NAME [--set ...] every setting of a scene, as --set would write it
    tissue info [--arch A]      backend, device, precision, library versions

Errors are one line on stderr: exit code 2 for bad input (unknown scene or field, bad value, missing
file), 1 for a failure while running (e.g. a diverging simulation); --debug shows the traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

# Taichi prints a banner when imported and a line when initialised; the command reports the
# backend itself (set ENABLE_TAICHI_HEADER_PRINT=true, or use --debug, to see Taichi's own).
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")
# BLAS on one thread unless OPENBLAS_NUM_THREADS says otherwise: OpenBLAS's threads wait on each
# other whenever the cores are busy (Taichi's own threads, other processes), and then a dense
# factorisation of a few hundred rows at start-up (the rest compliance) takes seconds instead of
# milliseconds (bench/blas_threads.py). Read when numpy and scipy load it: before any import of them.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from . import __version__  # noqa: E402
from .errors import TissueError  # noqa: E402

BAD_INPUT, RUNTIME_FAILURE = 2, 1


class InputError(TissueError):
    """A TissueError raised before the simulation steps: the user's input is at fault."""


class Progress:
    """A one-line progress bar on stderr, shown only on a terminal and only once a task has run
    longer than `delay` seconds."""

    def __init__(self, label: str, stream=None, delay: float = 2.0, width: int = 30):
        self.label, self.stream, self.delay, self.width = label, stream or sys.stderr, delay, width
        self.start = time.perf_counter()
        self.last_draw = 0.0
        self.drawn = False
        self.enabled = hasattr(self.stream, "isatty") and self.stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        elapsed = now - self.start
        if elapsed < self.delay or (now - self.last_draw < 0.1 and done < total):
            return
        self.last_draw = now
        fraction = done / total if total else 1.0
        filled = int(round(self.width * fraction))
        eta = elapsed * (1 - fraction) / fraction if fraction > 0 else 0.0
        self.stream.write(f"\r{self.label:<10} [{'#' * filled}{'-' * (self.width - filled)}] "
                          f"{done}/{total}  {elapsed:5.1f} s  eta {eta:4.0f} s ")
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.drawn:
            self.stream.write("\n")
            self.stream.flush()
            self.drawn = False


# ---- commands ----------------------------------------------------------------------------------


def _init_backend(args):
    """The backend of --arch/--precision, Taichi's own start-up line hidden unless --debug."""
    from . import backend

    quiet = contextlib.nullcontext() if args.debug else contextlib.redirect_stdout(io.StringIO())
    try:
        with quiet:
            return backend.init(args.arch, args.precision)
    except TissueError as err:
        raise InputError(str(err)) from None


def _load_scene(name: str, assignments):
    import scenes

    try:
        cls = scenes.load(name)
        scene = cls().with_overrides(assignments or [])
        from .options import validate

        return cls, validate(scene)
    except TissueError as err:
        raise InputError(str(err)) from None


def cmd_run(args) -> int:
    cls, scene = _load_scene(args.name, args.set)
    if args.steps is not None and args.steps < 1:
        raise InputError(f"--steps: must be >= 1, got {args.steps}")
    steps = args.steps if args.steps is not None else scene.steps
    name = Path(args.name).stem if args.name.endswith(".py") else args.name
    out = Path(args.out) if args.out else Path("out") / name
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")

    from . import compilation
    from .output import RunOutput
    from .simulation import Simulation

    started, compiled_at_start = time.perf_counter(), compilation.snapshot()
    _init_backend(args)
    try:
        sim = Simulation(scene, arch=args.arch, precision=args.precision)
        output = RunOutput(sim, out, steps, render=not args.no_render)
    except TissueError as err:
        raise InputError(str(err)) from None
    bodies = ", ".join(f"{n} ({b.mesh.n_points} nodes, {b.mesh.n_tets} tets, {len(b.fixed)} held)"
                       for n, b in sim.bodies.items())
    print(f"{name}: {bodies}; {steps} steps of {scene.dt:g} s on {sim.backend.arch} ({sim.backend.precision})",
          flush=True)
    built, compiled_at_built = time.perf_counter(), compilation.snapshot()
    output.record()
    bar = Progress("simulate")
    try:
        sim.run(steps, progress=bar, callback=output)
    finally:
        bar.close()
    simulated, compiled_at_simulated = time.perf_counter(), compilation.snapshot()
    build_compile = (compiled_at_built - compiled_at_start).seconds
    run_compile = (compiled_at_simulated - compiled_at_built).seconds
    bar = Progress("render")
    try:
        written = output.finish(extra=dict(scene=name, description=cls.description(), tissue=__version__,
                                           build_seconds=round(built - started, 3),
                                           run_seconds=round(simulated - built, 3),
                                           build_compile_seconds=round(build_compile, 3),
                                           run_compile_seconds=round(run_compile, 3)),
                                progress=bar)
    finally:
        bar.close()
    finished, compiled = time.perf_counter(), compilation.snapshot() - compiled_at_start
    print(sim.timing_table())
    line = _cg_line(sim)
    if line:
        print(line)
    # Kernels compile on their first launch, in whichever phase that falls: taken out of the
    # phases and shown on their own, so that the phases add up to the command's wall time.
    output_compile = compiled.seconds - build_compile - run_compile
    print(f"time: build {built - started - build_compile:.1f} s (mesh {sim.mesh_seconds:.1f} s), "
          f"compile {compiled.seconds:.1f} s ({compiled.count} kernels: {compiled.ir_seconds:.1f} s to module, "
          f"{compiled.machine_code_seconds:.1f} s machine code), "
          f"simulate {simulated - built - run_compile:.1f} s, output {finished - simulated - output_compile:.1f} s")
    shown = [str(p.relative_to(out)) for p in written if p.is_relative_to(out)]
    vtu = sum(len(series.steps) for series in output.series.values()) if output.series is not None else 0
    print(f"wrote {out}/: {', '.join(shown)}" + (f" (+{vtu} .vtu files)" if vtu else ""))
    return 0


def _cg_line(sim) -> str | None:
    """The run's CG summary: iterations per step (over bodies and steps), and the largest relative
    residual of the solves that the residual rule or the cap ended, the run's worst, not its last;
    those that SOFA's denominator rule ended, a body at rest (ImplicitEuler.record_step), apart."""
    solves = [body.solver.stats.history for body in sim.bodies.values()]
    iterations = [i for h in solves for i in h.get("cg_iterations", [])]
    if not iterations:
        return None
    residuals, at_rest = [], 0
    for h in solves:
        for residual, rest in zip(h["cg_residual"], h["cg_threshold_stop"]):
            at_rest += rest
            if not rest:
                residuals.append(residual)
    line = (f"CG: {statistics.median(iterations):.0f} iterations per step (median; at most {max(iterations):.0f}), "
            f"relative residual ‖r‖/‖b‖ at most {max(residuals, default=0.0):.1e} over the run")
    if at_rest:
        line += f" ({at_rest} solves with b at rounding level, a body at rest, ended by |pᵀAp| ≤ threshold)"
    return line


def cmd_list(args) -> int:
    import scenes

    try:
        catalogue = scenes.catalogue()
    except TissueError as err:
        raise InputError(str(err)) from None
    width = max(len(n) for n in catalogue) if catalogue else 0
    for name, cls in catalogue.items():
        print(f"{name:<{width}}  {cls.description()}")
    return 0


def cmd_show(args) -> int:
    from .options import flatten, format_value

    cls, scene = _load_scene(args.name, args.set)
    print(f"# {args.name}: {cls.description()}  ({scene.steps} steps)")
    for key, value in flatten(scene).items():
        print(f"{key}={format_value(value)}")
    return 0


def _version(package: str) -> str:
    from importlib import metadata      # here: `tissue run` need not import it

    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _device(arch: str) -> str:
    if arch == "cuda":
        import subprocess

        try:
            result = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
                                    capture_output=True, text=True, timeout=10)
            if result.returncode == 0 and result.stdout.strip():
                return result.stdout.strip().splitlines()[0]
        except (OSError, subprocess.SubprocessError):
            pass
        return "CUDA device"
    if arch == "vulkan":
        return "Vulkan device"
    return f"{_cpu_name()} ({os.cpu_count()} logical cores)"


def cmd_info(args) -> int:
    print(f"tissue {__version__}  (python {platform.python_version()}, {sys.executable})")
    be = _init_backend(args)
    requested = args.arch or os.environ.get("TISSUE_ARCH") or "auto"
    print(f"backend    {be.arch} (requested {requested})")
    print(f"precision  {be.precision}")
    import taichi as ti

    from .backend import ir_passes

    passes = {"auto": "per kernel (off for the multigrid step kernels)", "1": "on", "0": "off"}[ir_passes()]
    print(f"IR passes  {passes} (Taichi's advanced_optimization; TISSUE_ADVANCED_OPTIMIZATION=0|auto|1)")
    cfg = ti.lang.impl.current_cfg()
    print(f"cache      {cfg.offline_cache_file_path} (Taichi's offline cache, at most "
          f"{cfg.offline_cache_max_size_of_files >> 20} MiB)")
    print(f"device     {_device(be.arch)}")
    print("libraries  " + ", ".join(f"{p} {_version(p)}" for p in
                                    ("taichi", "numpy", "scipy", "meshio", "pyvista", "vtk", "open3d")))
    return 0


# ---- parsing and error handling ------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the traceback of an error")
    parser = argparse.ArgumentParser(prog="tissue", parents=[common],
                                     description="Real-time soft-tissue simulation: co-rotational implicit FEM.")
    parser.add_argument("--version", action="version", version=f"tissue {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    backend_args = argparse.ArgumentParser(add_help=False)
    backend_args.add_argument("--arch", choices=("auto", "cpu", "cuda", "vulkan"), default=None,
                              help="Taichi backend (default: $TISSUE_ARCH, else auto: CUDA if present)")
    backend_args.add_argument("--precision", choices=("f64", "f32"), default=None,
                              help="floating-point precision (default: $TISSUE_PRECISION, else f64)")
    overrides = argparse.ArgumentParser(add_help=False)
    overrides.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                           help="override a scene setting, e.g. --set liver.young=5e3 --set dt=0.04 "
                                "(see `tissue show NAME`)")

    run = sub.add_parser("run", parents=[common, backend_args, overrides], help="run a scene",
                         description="Run a scene and write its figure, frames, animation, VTU series "
                                     "and stats.json under --out.")
    run.add_argument("name", metavar="NAME", help="a scene of `tissue list`, or a scene module file (.py)")
    run.add_argument("--steps", type=int, default=None, help="number of steps (default: duration / dt)")
    run.add_argument("--out", default=None, metavar="DIR", help="output folder (default: out/NAME)")
    run.add_argument("--no-render", action="store_true",
                     help="write no images (VTU series and stats.json only; pyvista is not imported)")
    run.set_defaults(func=cmd_run)

    listing = sub.add_parser("list", parents=[common], help="list the scenes")
    listing.set_defaults(func=cmd_list)

    show = sub.add_parser("show", parents=[common, overrides], help="print a scene's settings")
    show.add_argument("name", metavar="NAME")
    show.set_defaults(func=cmd_show)

    info = sub.add_parser("info", parents=[common, backend_args], help="backend, device and versions")
    info.set_defaults(func=cmd_info)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # argparse has printed its usage line and message
        return int(exit_.code or 0)
    try:
        return args.func(args)
    except InputError as err:
        if args.debug:
            traceback.print_exc()
        print(f"tissue: error: {err}", file=sys.stderr)
        return BAD_INPUT
    except TissueError as err:
        if args.debug:
            traceback.print_exc()
        print(f"tissue: error: {err}", file=sys.stderr)
        return RUNTIME_FAILURE
    except KeyboardInterrupt:
        print("tissue: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `tissue show liver | head`: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except Exception as err:  # noqa: BLE001 - one line unless --debug
        if args.debug:
            traceback.print_exc()
        print(f"tissue: internal error: {type(err).__name__}: {err} (rerun with --debug for the traceback)",
              file=sys.stderr)
        return RUNTIME_FAILURE


if __name__ == "__main__":
    sys.exit(main())
