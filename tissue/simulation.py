"""The Simulation that builds only what a scene declares, and the stages of a step.

Simulation(scene, arch=None, precision=None)
    initialises the backend (`tissue.backend.init`), builds each soft body (`tissue.body.Body`:
    mesh, `CorotationalFEM`, `ImplicitEuler`, its held nodes and boundary triangles) and then the
    stages of a step, from the list `STAGES`. `.step()` runs the stages in order, timing each in
    `.stats` (a `tissue.stats.Stats`: per-stage wall time and counters, the bodies' own stages
    merged in as "stage: sub-stage"); `.run(steps, progress=..., callback=...)`; `.state()` gives
    numpy arrays for output. The one-off costs are apart: `.mesh_seconds` (building the meshes)
    and `.compiled()` (kernel compilation since the simulation began; `.compile_seconds_by_step`:
    its share in each step).

How a later layer plugs in (contact, attachments, haptics, cutting)
    1. Its settings are an `Options` dataclass in its own package (e.g. `tissue.contact.Contact`);
       the scenes that use it declare a field of that type (`contact: Contact = field(...)`).
       Scenes that do not declare it are untouched: nothing here names the layer.
    2. A stage is any object with a `name` and `step(sim)`; it may also have `report()` returning
       ({sub-stage: seconds of the last step}, {counter: value}) to be merged into `sim.stats`, and
       `drawables()` returning the rigid things it wants in the run's images (`Drawable`: a surface
       in its own frame and a pose over time; `tissue.output` draws and moves them without knowing
       what they are, e.g. the contact layer's obstacles), and `write_outputs(directory, figures)` writing
       its own files beside the images (the haptics stage's force log and plot), returning their paths.
    3. A builder `build(sim) -> stage | None` returns the stage only when the scene declares the
       layer (`sim.scene.parts(Contact)` lists such fields), and is registered at its place in the
       data flow of DESIGN.md (free motion, detection, compliance, LCP, correction, hand-off,
       topology) with `add_stage(build, after="free_motion")` when the layer's module is imported
       (which a scene module naming the layer's Options type does); builders run in that order and
       may look at the stages built before them (`sim.stages`). A scene without contact thus
       builds no contact stage and allocates nothing for it.
    Rigid obstacles follow the same pattern as soft bodies: an `Obstacle` Options type, found among
    the scene's fields with `scene.parts(Obstacle)`.
"""

from __future__ import annotations

import gc
from dataclasses import dataclass, replace
from typing import Callable, Protocol

import numpy as np

from . import backend, compilation
from .body import Body, mesh_seconds
from .errors import TissueError
from .options import validate
from .scene import Scene
from .stats import Stats

__all__ = ["Simulation", "Stage", "Drawable", "FreeMotion", "STAGES", "add_stage"]


class Stage(Protocol):
    """One stage of a step (free motion, contact detection, ...)."""

    name: str

    def step(self, sim: "Simulation") -> None: ...


@dataclass
class Drawable:
    """A rigid shape a stage asks the run output to draw (an obstacle), given in its own frame.

    surface(bounds) -> (points (n, 3), triangles (k, 3)); `bounds` = (xmin, xmax, ymin, ymax, zmin,
    zmax) of the soft bodies over the run, for shapes with no extent of their own (a plane is drawn
    as a patch around the bodies). pose(time) -> 4×4 transform to the world; `moving`: it changes
    over time (else the pose at time 0 holds). framed: counts when framing the camera (a large
    plane should not). color: None for the renderer's obstacle grey. flat: one unlit tone, like the
    floor (a large plane), rather than shaded.
    """

    name: str
    surface: Callable[[tuple], tuple[np.ndarray, np.ndarray]]
    pose: Callable[[float], np.ndarray]
    moving: bool = False
    framed: bool = True
    color: str | None = None
    flat: bool = False


class FreeMotion:
    """Step 1 of the data flow: every soft body advances alone (implicit Euler, matrix-free CG)."""

    name = "free_motion"

    def __init__(self, bodies: list[Body]):
        self.bodies = bodies

    def step(self, sim: "Simulation") -> None:
        for body in self.bodies:
            try:
                body.stepper.step()
            except TissueError as err:
                raise TissueError(f"{body.name}: {err}") from None

    def report(self) -> tuple[dict[str, float], dict[str, float]]:
        """Seconds of the last step by sub-stage (summed over bodies) and counters: per body
        (liver.cg_iterations) and over bodies (cg_iterations: the most, cg_residual: the largest)."""
        seconds: dict[str, float] = {}
        counters: dict[str, float] = {}
        for body in self.bodies:
            for sub, times in body.solver.stats.times.items():
                if times:
                    seconds[sub] = seconds.get(sub, 0.0) + times[-1]
            for key, value in body.solver.stats.counters.items():
                counters[f"{body.name}.{key}"] = value
                counters[key] = max(counters.get(key, value), value)
        return seconds, counters


def free_motion(sim: "Simulation") -> Stage | None:
    bodies = list(sim.bodies.values())
    return FreeMotion(bodies) if bodies else None


# The builders of a step's stages, in data-flow order; each returns a stage or None (not declared).
STAGES: list[Callable[["Simulation"], Stage | None]] = [free_motion]


def add_stage(builder: Callable[["Simulation"], Stage | None], after: str | None = None) -> None:
    """Register a stage builder, after the builder function named `after` (default: last)."""
    if builder in STAGES:
        return
    names = [b.__name__ for b in STAGES]
    if after is None:
        STAGES.append(builder)
    elif after in names:
        STAGES.insert(names.index(after) + 1, builder)
    else:
        raise TissueError(f"add_stage: no stage builder named {after!r}; known: {', '.join(names)}")


class Simulation:
    """The bodies and stages a scene declares, stepped together (see the module docstring)."""

    def __init__(self, scene: Scene, arch: str | None = None, precision: str | None = None):
        if not isinstance(scene, Scene):
            raise TissueError(f"Simulation: expected a Scene, got {type(scene).__name__}")
        self.scene = validate(scene)
        self._compiled_before = compilation.snapshot()
        self.backend = backend.init(arch, precision)
        meshes_before = mesh_seconds()
        self.bodies: dict[str, Body] = {name: Body(name, spec, scene) for name, spec in scene.bodies().items()}
        self.mesh_seconds = mesh_seconds() - meshes_before
        self.compile_seconds_by_step: list[float] = []
        self.stages: list[Stage] = []          # built in order: a builder may look at the stages before it
        for build in STAGES:
            stage = build(self)
            if stage is not None:
                self.stages.append(stage)
        self.stats = Stats()
        self.time = 0.0
        self.step_count = 0

    @property
    def dt(self) -> float:
        return self.scene.dt

    def step(self) -> None:
        compiled_before = compilation.seconds()
        for stage in self.stages:
            with self.stats.stage(stage.name):
                stage.step(self)
            report = getattr(stage, "report", None)
            if report is not None:
                seconds, counters = report()
                for sub, value in seconds.items():
                    self.stats.times[f"{stage.name}: {sub}"].append(value)
                if counters:
                    self.stats.count(**counters)
        self.compile_seconds_by_step.append(compilation.seconds() - compiled_before)
        self.step_count += 1
        self.time += self.scene.dt

    def set_parameters(self, **changes) -> None:
        """Change the step's parameters on the live simulation, from the next step on, compiling
        nothing: `dt`, `gravity`, and the `solver` group's `cg_iterations`, `cg_tolerance`,
        `cg_warm_start`, `rayleigh_mass`, `rayleigh_stiffness` (e.g. `sim.set_parameters(dt=0.01, cg_iterations=50)`).
        The contact stage's compliance is built for one step matrix, so with contact dt and
        damping stay as built."""
        scene_fields, solver_fields = {"dt", "gravity"}, {"cg_iterations", "cg_tolerance", "cg_warm_start",
                                                          "rayleigh_mass", "rayleigh_stiffness"}
        unknown = sorted(set(changes) - scene_fields - solver_fields)
        if unknown:
            raise TissueError(f"{unknown[0]}: not a parameter a live simulation can change; "
                              f"expected {', '.join(sorted(scene_fields | solver_fields))}")
        solver = replace(self.scene.solver, **{k: v for k, v in changes.items() if k in solver_fields})
        scene = validate(replace(self.scene, solver=solver, **{k: v for k, v in changes.items() if k in scene_fields}))
        matrix_changes = [k for k in ("dt", "rayleigh_mass", "rayleigh_stiffness") if k in changes]
        if matrix_changes and any(stage.name != "free_motion" for stage in self.stages):
            raise TissueError(f"{matrix_changes[0]}: the contact stage's compliance is built for the step "
                              f"matrix at dt={self.scene.dt}; build a new Simulation to change it")
        parameters = solver.parameters(scene)
        for body in self.bodies.values():
            body.solver.set_parameters(**vars(parameters))
        self.scene = scene

    def run(self, steps: int | None = None, progress: Callable[[int, int], None] | None = None,
            callback: Callable[["Simulation"], None] | None = None) -> None:
        """`steps` steps (default: the scene's duration / dt); after each, `callback(sim)` and
        `progress(done, steps)`. The objects alive before the run are frozen for its length
        (`gc.freeze`, after a collection of what is garbage already): the collector's full passes,
        about one in 1,000 steps of the floor scene, walked them all and stopped that step for
        tens of ms. They are unfrozen after, so that what becomes garbage later is still freed."""
        steps = self.scene.steps if steps is None else int(steps)
        if steps < 0:
            raise TissueError(f"steps: must be >= 0, got {steps}")
        gc.collect()
        gc.freeze()
        try:
            for i in range(steps):
                self.step()
                if callback is not None:
                    callback(self)
                if progress is not None:
                    progress(i + 1, steps)
        finally:
            gc.unfreeze()

    def state(self) -> dict[str, dict[str, np.ndarray]]:
        """{body: {positions, velocities, displacement}} as float64 numpy arrays."""
        out = {}
        for name, body in self.bodies.items():
            x = body.positions()
            out[name] = dict(positions=x, velocities=body.velocities(), displacement=x - body.rest)
        return out

    def ms_per_step(self, skip: int = 1) -> dict[str, float]:
        """Median ms per step of each stage and sub-stage ("stage: sub"), leaving out `skip` warm-up steps."""
        return self.stats.ms_per_step(skip)

    def compiled(self) -> compilation.Compiled:
        """Kernel compilation in this process since this simulation began: its build, steps and
        output (and whatever else compiled meanwhile)."""
        return compilation.snapshot() - self._compiled_before

    def timing_table(self, skip: int = 1) -> str:
        """Median ms per step by stage, sub-stages indented under their stage; then the one-off
        costs: mesh generation and kernel compilation (with how much of it fell in the steps)."""
        ms = self.ms_per_step(skip)
        rows = [(("  " + k.split(": ", 1)[1]) if ": " in k else k, v) for k, v in ms.items()]
        width = max([len(r[0]) for r in rows] + [len("kernel compilation")])
        warm_up = "step 1" if skip == 1 else f"steps 1-{skip}"
        left_out = 0 < skip < self.step_count
        lines = [f"{'stage':<{width}}  ms/step (median{f', {warm_up} left out' if left_out else ''})"]
        lines += [f"{k:<{width}}  {v:10.3f}" for k, v in rows]
        lines.append(f"{'total':<{width}}  {sum(v for k, v in ms.items() if ': ' not in k):10.3f}")
        compiled, in_steps = self.compiled(), self.compile_seconds_by_step
        where = f"{sum(in_steps):.3f} s of it in the steps"
        if left_out:
            where += f", {sum(in_steps[:skip]):.3f} s in {warm_up}"
        lines.append(f"{'mesh generation':<{width}}  {self.mesh_seconds:10.3f} s")
        lines.append(f"{'kernel compilation':<{width}}  {compiled.seconds:10.3f} s  ({compiled.count} kernels; {where})")
        lines.append(f"{'  source to module':<{width}}  {compiled.ir_seconds:10.3f} s  (Taichi IR, LLVM module or the offline cache)")
        lines.append(f"{'  machine code':<{width}}  {compiled.machine_code_seconds:10.3f} s  (at first launch: not cached)")
        return "\n".join(lines)

    def summary(self) -> dict:
        """Sizes, timings and counters, JSON-ready."""
        history = self.stats.history
        return dict(
            arch=self.backend.arch, precision=self.backend.precision, dt=self.scene.dt,
            steps=self.step_count, time=self.time,
            bodies={n: dict(nodes=b.mesh.n_points, tets=b.mesh.n_tets, held=len(b.fixed))
                    for n, b in self.bodies.items()},
            stages=[s.name for s in self.stages],
            mesh_generation_seconds=round(self.mesh_seconds, 4),
            kernel_compilation_seconds=round(self.compiled().seconds, 4),
            kernel_compilation_ir_seconds=round(self.compiled().ir_seconds, 4),
            kernel_compilation_machine_code_seconds=round(self.compiled().machine_code_seconds, 4),
            kernels_compiled=self.compiled().count,
            kernel_compilation_seconds_in_steps=round(sum(self.compile_seconds_by_step), 4),
            ms_per_step=self.ms_per_step(),
            ms_per_step_mean={k: 1e3 * float(np.mean(v[1:] if len(v) > 1 else v))
                              for k, v in self.stats.times.items() if v},
            counters_last=dict(self.stats.counters),
            counters_mean={k: float(np.mean(v)) for k, v in history.items() if v},
            counters_max={k: float(np.max(v)) for k, v in history.items() if v},
        )
