"""What a run leaves in its output folder.

    figure.png                the flagship frame (render.figure: a fraction of the run), full size
    frame_NNNNNN.png          stills at render.stills (fractions of the run; first, middle, last)
    animation.gif / .mp4      every render.every steps, at render.animation_size
    vtu/BODY.pvd + .vtu       a ParaView series: displacement (vector and magnitude), held nodes,
                              von Mises stress per element
    stats.json                ms per step by stage, counters, sizes, the scene's settings

Only these names are written: nothing else in the folder is touched or deleted. States are recorded
during the run (positions, and stresses when needed) and rendered at the end, so the colour range
and the camera frame cover the whole motion. pyvista is imported only when rendering. Rigid things
the stages declare (`drawables()`, see `tissue.simulation.Drawable`: the contact layer's obstacles)
are drawn in every image and follow their prescribed motion; a stage's `write_outputs(directory)`
adds its own files (the haptics stage's forces.csv, and forces.png with png output).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .errors import TissueError
from .options import flatten
from .simulation import Simulation

LENGTH_UNITS = ((1.0, "m", 1.0), (1e-3, "mm", 1e3))      # (threshold, name, factor), largest first
STRESS_UNITS = ((1e6, "MPa", 1e-6), (1e3, "kPa", 1e-3), (0.0, "Pa", 1.0))
INNER_COLOR = "#8e2f2a"      # the faces of a cut: an organ's darker inside


def nice_ceiling(x: float) -> float:
    """The smallest of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 (times a power of ten) that is >= x."""
    if not x > 0:
        return 1.0
    power = 10.0 ** np.floor(np.log10(x))
    for m in (1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10):
        if m * power >= x * (1 - 1e-9):
            return m * power
    return 10 * power


def _unit(value: float, units) -> tuple[str, float]:
    for threshold, name, factor in units:
        if value >= threshold:
            return name, factor
    return units[-1][1], units[-1][2]


class Frame:
    """One recorded state: step, time, and per body its positions, element von Mises stress and
    topology (rest points, boundary faces, mask of those on a cut: changed by cutting)."""

    __slots__ = ("step", "time", "positions", "von_mises", "topology")

    def __init__(self, step, time, positions, von_mises, topology):
        self.step, self.time, self.positions, self.von_mises = step, time, positions, von_mises
        self.topology = topology


class RunOutput:
    """Records a simulation's states at the chosen steps and writes the run's files at `finish()`.

    Use as the callback of `Simulation.run` (it records the steps it wants), after recording the
    initial state with `record()`.
    """

    def __init__(self, sim: Simulation, directory, steps: int, render: bool = True):
        self.sim, self.directory, self.steps = sim, Path(directory), int(steps)
        settings = sim.scene.render
        self.settings = settings
        self.outputs = set(settings.outputs) if render else set(settings.outputs) & {"vtu"}
        self.rendering = bool(self.outputs & {"png", "gif", "mp4"})
        every = settings.every
        self.animation_steps = sorted(set(range(0, self.steps + 1, every)) | {self.steps})
        self.still_steps = sorted({round(f * self.steps) for f in settings.stills})
        self.figure_step = round(settings.figure * self.steps)
        wanted = set(self.animation_steps) if ("vtu" in self.outputs or self.outputs & {"gif", "mp4"}) else set()
        if "png" in self.outputs:
            wanted |= set(self.still_steps) | {self.figure_step}
        self.wanted = wanted | {0, self.steps}
        self.need_stress = "vtu" in self.outputs or (self.rendering and settings.scalars == "von_mises")
        self.frames: list[Frame] = []
        # Rigid things the stages want drawn (tissue.simulation.Drawable; e.g. the contact obstacles).
        self.drawables = [d for stage in sim.stages for d in (getattr(stage, "drawables", None) or list)()]
        self._surfaces = None
        self.seconds = {"record": 0.0, "render": 0.0}
        self.written: list[Path] = []
        self.series = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise TissueError(f"--out {self.directory}: cannot create the folder ({err.strerror})") from None
        if "vtu" in self.outputs:
            from .mesh import PvdSeries

            self.series = {name: PvdSeries(self.directory / "vtu", name) for name in sim.bodies}

    # ---- during the run -------------------------------------------------------------------------

    def __call__(self, sim: Simulation) -> None:
        if sim.step_count in self.wanted:
            self.record()

    def record(self) -> None:
        """Record the simulation's current state (and write its VTU files)."""
        start = time.perf_counter()
        sim = self.sim
        positions, stresses = {}, {}
        for name, body in sim.bodies.items():
            positions[name] = body.positions()
            stresses[name] = body.von_mises() if self.need_stress else None
            if self.series is not None:
                u = positions[name] - body.rest
                held = np.zeros(body.mesh.n_points, dtype=np.int32)
                held[body.fixed] = 1
                self.series[name].write(
                    sim.time, positions[name], body.mesh.tets,
                    point_data={"displacement": u, "displacement_magnitude": np.linalg.norm(u, axis=1),
                                "held": held},
                    cell_data={"von_mises": stresses[name]})
        self.frames.append(Frame(sim.step_count, sim.time, positions, stresses,
                                 {name: body.topology for name, body in sim.bodies.items()}))
        self.seconds["record"] += time.perf_counter() - start

    # ---- at the end ------------------------------------------------------------------------------

    def finish(self, extra: dict | None = None, progress=None) -> list[Path]:
        """Render (if asked), write stats.json; returns the files written."""
        if self.series is not None:
            self.written += [s.pvd_path for s in self.series.values()]
        if self.rendering and self.frames:
            start = time.perf_counter()
            self._render(progress)
            self.seconds["render"] = time.perf_counter() - start
        for stage in self.sim.stages:      # a stage's own files (the haptics stage's force log and plot)
            writer = getattr(stage, "write_outputs", None)
            if writer is not None:
                self.written += writer(self.directory, figures="png" in self.outputs)
        self.written.append(self.write_stats(extra or {}))
        return self.written

    def write_stats(self, extra: dict) -> Path:
        sim = self.sim
        summary = sim.summary()
        data = dict(extra)
        data.update(summary)
        data["output_seconds"] = {k: round(v, 4) for k, v in self.seconds.items()}
        data["files"] = sorted(str(p.relative_to(self.directory)) for p in self.written
                               if p.is_relative_to(self.directory))
        data["scene_settings"] = flatten(sim.scene)
        path = self.directory / "stats.json"
        path.write_text(json.dumps(data, indent=2, default=_jsonable) + "\n")
        return path

    # ---- rendering ----------------------------------------------------------------------------

    def _scalars(self):
        """(title, per-frame per-body nodal values, clim) for the colouring, or None."""
        kind = self.settings.scalars
        sim = self.sim
        if kind is None:
            return None
        values = []
        for frame in self.frames:
            per_body = {}
            for name, body in sim.bodies.items():
                if kind == "displacement":
                    per_body[name] = np.linalg.norm(frame.positions[name] - frame.topology[name][0], axis=1)
                else:
                    per_body[name] = body.nodal(frame.von_mises[name])
            values.append(per_body)
        everything = np.concatenate([v for per_body in values for v in per_body.values()])
        # Stress is singular at held nodes: the range stops at the 99th percentile (the peaks
        # saturate) so the rest of the body is not all one colour. Displacement uses its maximum.
        top = float(np.percentile(everything, 99.0) if kind == "von_mises" else np.max(everything))
        if kind == "displacement":
            unit, factor = _unit(top, LENGTH_UNITS)
            title = f"displacement [{unit}]"
        else:
            unit, factor = _unit(top, STRESS_UNITS)
            title = f"von Mises stress [{unit}]"
        values = [{k: v * factor for k, v in per_body.items()} for per_body in values]
        return title, values, (0.0, nice_ceiling(top * factor))

    def _bounds(self, bodies_only: bool = False) -> np.ndarray:
        """(xmin, xmax, ymin, ymax, zmin, zmax) of the bodies over the recorded frames, and of the
        framed drawables (obstacles) where they are in those frames."""
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for frame in self.frames:
            for x in frame.positions.values():
                lo = np.minimum(lo, x.min(axis=0))
                hi = np.maximum(hi, x.max(axis=0))
        if not bodies_only:
            bodies = np.stack([lo, hi], axis=1).ravel()
            for d, (points, _) in zip(self.drawables, self._drawable_surfaces(bodies)):
                if not d.framed:
                    continue
                for frame in (self.frames if d.moving else self.frames[:1]):
                    T = np.asarray(d.pose(frame.time))
                    world = points @ T[:3, :3].T + T[:3, 3]
                    lo, hi = np.minimum(lo, world.min(axis=0)), np.maximum(hi, world.max(axis=0))
        return np.stack([lo, hi], axis=1).ravel()

    def _drawable_surfaces(self, body_bounds):
        if self._surfaces is None:
            self._surfaces = [d.surface(tuple(body_bounds)) for d in self.drawables]
        return self._surfaces

    def _renderer(self, size, bounds, colouring, title):
        from .render import Renderer

        s = self.settings
        renderer = Renderer(size=size, camera=s.camera, up="z", bounds=bounds, edges=s.edges,
                            ground=s.ground, title=title or None, zoom=s.zoom)
        self._shown = {}
        for name in self.sim.bodies:
            points, faces, scalars = self._drawn(name, 0, colouring)
            if colouring is None:
                renderer.add_body(name, points, faces)
            else:
                renderer.add_body(name, points, faces, scalars=scalars, scalar_name=colouring[0], clim=colouring[2])
            self._show_cut(renderer, name, 0)
        if s.ghost:  # the rest shape, faint and without a shadow, drawn straight on the plotter
            import pyvista as pv

            for name in self.sim.bodies:
                points, faces, _ = self._drawn(name, 0, None)
                ghost = pv.PolyData.from_regular_faces(points, np.asarray(faces, dtype=np.int64))
                renderer.plotter.add_mesh(ghost, name=f"ghost:{name}", color="#8a8f96", opacity=0.18,
                                          smooth_shading=True, specular=0.0)
        for d, surface in zip(self.drawables, self._drawable_surfaces(self._bounds(bodies_only=True))):
            renderer.add_obstacle(d.name, surface, color=d.color, framed=d.framed, lit=not d.flat)
            renderer.update_obstacle(d.name, transform=d.pose(self.frames[0].time))
        markers = self._markers(bounds)
        if markers is not None:
            renderer.add_obstacle("held nodes", markers, color="#303030", framed=False)
        return renderer

    def _markers(self, bounds):
        """Small dark spheres on the held nodes (they do not move); none beyond 500 of them, where
        they would only cover the body (a clamped face shows in the colours anyway)."""
        import pyvista as pv

        if sum(len(body.fixed) for body in self.sim.bodies.values()) > 500:
            return None

        extent = np.linalg.norm(np.asarray(bounds).reshape(3, 2) @ np.array([-1.0, 1.0]))
        radius = 0.008 * extent
        spheres = [pv.Sphere(radius=radius, center=body.rest[i], theta_resolution=16, phi_resolution=12)
                   for body in self.sim.bodies.values() for i in body.fixed]
        if not spheres:
            return None
        return pv.merge(spheres) if len(spheres) > 1 else spheres[0]

    def _drawn(self, name: str, index: int, colouring):
        """(points, triangles, scalars or None) of body `name` as drawn in frame `index`."""
        body = self.sim.bodies[name]
        x = self.frames[index].positions[name]
        scalars = None if colouring is None else colouring[1][index][name]
        visual = body.visual() if self.settings.visual == "surface" else None
        if visual is None:
            _, faces, cut = self.frames[index].topology[name]
            return x, faces[~cut], scalars
        return visual.points(x), visual.triangles, None if scalars is None else visual.values(scalars)

    def _show_cut(self, renderer, name: str, index: int) -> None:
        """The faces of a cut, drawn in the organ's inner colour as a body of their own."""
        topology = self.frames[index].topology[name]
        if self._shown.get(name) is topology:
            return
        self._shown[name] = topology
        _, faces, cut = topology
        drawn = f"{name} (cut)"
        if drawn in renderer.bodies:
            renderer.remove(drawn)
        if cut.any():
            renderer.add_body(drawn, self.frames[index].positions[name], faces[cut], color=INNER_COLOR)

    def _show(self, renderer, index: int, colouring) -> None:
        for name in self.sim.bodies:
            points, faces, scalars = self._drawn(name, index, colouring)
            reshaped = self._shown.get(name) is not self.frames[index].topology[name]
            renderer.update_body(name, points=points, scalars=scalars, faces=faces if reshaped else None)
            self._show_cut(renderer, name, index)
            if f"{name} (cut)" in renderer.bodies:
                renderer.update_body(f"{name} (cut)", points=self.frames[index].positions[name])
        for d in self.drawables:
            if d.moving:
                renderer.update_obstacle(d.name, transform=d.pose(self.frames[index].time))
        renderer.set_label(f"t = {self.frames[index].time:.2f} s")

    def _render(self, progress=None) -> None:
        s = self.settings
        scene = self.sim.scene
        title = s.title
        bounds = self._bounds()
        colouring = self._scalars()
        index = {f.step: i for i, f in enumerate(self.frames)}
        stills = [index[k] for k in self.still_steps if k in index] if "png" in self.outputs else []
        animated = [index[k] for k in self.animation_steps if k in index] if self.outputs & {"gif", "mp4"} else []
        total = len(stills) + (1 if "png" in self.outputs else 0) + len(animated)
        done = 0

        def tick():
            nonlocal done
            done += 1
            if progress is not None:
                progress(done, total)

        if "png" in self.outputs:
            renderer = self._renderer(s.size, bounds, colouring, title)
            try:
                self._show(renderer, index[self.figure_step], colouring)
                self.written.append(renderer.screenshot(self.directory / "figure.png"))
                tick()
                for i in stills:
                    self._show(renderer, i, colouring)
                    self.written.append(renderer.screenshot(self.directory / f"frame_{self.frames[i].step:06d}.png"))
                    tick()
            finally:
                renderer.close()
        if animated:
            paths = [self.directory / f"animation.{kind}" for kind in ("gif", "mp4") if kind in self.outputs]
            fps = s.fps if s.fps > 0 else 1.0 / (s.every * scene.dt)
            renderer = self._renderer(s.animation_size, bounds, colouring, title)
            try:
                from .render import Animation
                from .render.writers import GifWriter, Mp4Writer

                animation = Animation(renderer, [
                    GifWriter(p, fps=fps, width=None, palette="per-frame") if p.suffix == ".gif"
                    else Mp4Writer(p, fps=fps) for p in paths])
                for i in animated:
                    self._show(renderer, i, colouring)
                    animation.write_frame()
                    tick()
                self.written += animation.close()
            finally:
                renderer.close()


def _jsonable(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
