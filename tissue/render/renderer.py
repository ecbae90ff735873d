"""Offscreen figure renderer: soft bodies (surface triangles, optional scalars) and rigid obstacles.

The simulation owns the geometry; the renderer only receives numpy arrays: a body's current points
and its boundary triangles, optionally per-point or per-triangle scalars. Each frame replaces the
points (and scalars) of meshes already in the scene, so an animation costs one render per frame
and nothing is rebuilt. The camera is fixed at the first render (or from given bounds), so an
animation does not jitter as the bodies move.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyvista as pv

from ..errors import TissueError
from .camera import camera_position, up_vector
from .writers import flatten, write_png, writer_for

# Tissue-like colours for bodies drawn without scalars, in the order they are added.
BODY_COLORS = ["#c46a5a", "#d8a05a", "#8a6fb0", "#6f9f7a", "#5f8fc0", "#c07a9a"]
OBSTACLE_COLOR = "#a9adb3"  # neutral grey: rigid things must not compete with the tissue
GROUND_COLOR = "#f0f0f0"
SHADOW_COLOR = "#d2d2d2"
EDGE_COLOR = "#3a3a3a"
BAR_FREE_WIDTH = 0.82  # fraction of the image width left of a colour bar


@dataclass
class _Item:
    mesh: pv.PolyData
    actor: object
    scalar_name: str | None = None
    framed: bool = True  # counts when framing the camera
    shadow: pv.PolyData | None = None  # its drop shadow on the ground, if there is a ground
    reshaped: bool = False  # its faces changed since the shadow was made (a cut body)


def _label_count(lo: float, hi: float) -> int:
    """How many colour-bar labels make round steps (1, 2 or 5 times a power of ten) over [lo, hi]."""
    for n in (5, 6, 4, 3, 7):
        step = (hi - lo) / (n - 1)
        if step <= 0:
            break
        mantissa = step / 10 ** np.floor(np.log10(step))
        if any(np.isclose(mantissa, m) for m in (1, 2, 5, 10)) and np.isclose(lo / step, round(lo / step)):
            return n
    return 5


def _triangles(points, faces, what: str) -> pv.PolyData:
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces)
    if points.ndim != 2 or points.shape[1] != 3:
        raise TissueError(f"render: {what}: points must be (n, 3), got shape {points.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise TissueError(f"render: {what}: faces must be non-empty (k, 3) triangles, got shape {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(points):
        raise TissueError(f"render: {what}: face indices out of range [0, {len(points)})")
    return pv.PolyData.from_regular_faces(points, faces.astype(np.int64))


def _surface(surface, what: str) -> pv.PolyData:
    """Anything pyvista can wrap (or a (points, faces) pair) as a triangle surface."""
    if isinstance(surface, tuple) and len(surface) == 2:
        return _triangles(*surface, what)
    mesh = pv.wrap(surface)
    if mesh is None:
        raise TissueError(f"render: {what}: cannot draw a {type(surface).__name__}")
    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface()
    return mesh.triangulate()


class Renderer:
    """An offscreen scene of soft bodies and obstacles that writes figure-ready frames.

    size: image (width, height) in pixels. camera: a preset ('iso', 'front', 'side', 'top') or an
    (azimuth, elevation) pair in degrees. up: the scene's up axis ('y', 'z', '-z', or a vector).
    background: 'white', 'transparent' or any colour. bounds: (xmin, xmax, ymin, ymax, zmin, zmax)
    to frame instead of the scene's bounds at the first render. edges: draw triangle edges on
    bodies by default. ground: a light floor under the scene, fixed with the camera, on which every
    body and obstacle casts a drop shadow (straight down), so contact and height read at a glance.
    """

    def __init__(self, size=(1280, 960), camera="iso", up="y", background="white", bounds=None,
                 edges: bool = False, ground: bool = False,
                 title: str | None = None, anti_aliasing: str | None = "ssaa", zoom: float = 1.0):
        self.size = (int(size[0]), int(size[1]))
        self.camera, self.up, self.zoom = camera, up_vector(up), zoom
        self.edges, self.ground = edges, ground
        self._ground_height = None  # along `up`, set with the camera
        self.transparent = background == "transparent"
        self._bounds = None if bounds is None else tuple(float(b) for b in bounds)
        self._camera_fixed = False
        self._bodies: dict[str, _Item] = {}
        self._obstacles: dict[str, _Item] = {}
        self._bars: set[str] = set()
        # Text scales with the image so a figure reads the same at any resolution.
        self.font_size = max(8, round(self.size[1] / 60))
        # 'light kit' is pyvista's key/fill/back/head light arrangement, attached to the camera:
        # soft, even light from any preset. (VTK's shadow maps were tried for the ground shadow;
        # their frustum leaves hard dark bands, so shadows are projected geometry instead.)
        self.plotter = pv.Plotter(off_screen=True, window_size=list(self.size), lighting="light kit")
        self.plotter.set_background("white" if self.transparent else background)
        if anti_aliasing:
            self.plotter.enable_anti_aliasing(anti_aliasing)
        if title:
            self.set_title(title)

    # ---- scene composition ---------------------------------------------------------------------

    def add_body(self, name: str, points, faces, *, scalars=None, scalar_name: str | None = None,
                 clim=None, cmap: str = "viridis", color=None, edges: bool | None = None,
                 opacity: float = 1.0, smooth: bool = True) -> None:
        """A soft body from its current points (n, 3) and boundary triangles (k, 3).

        scalars: per point (n,) or per triangle (k,) values (points win when n == k), coloured with
        `cmap` and shown on a colour bar titled `scalar_name`; bodies sharing a scalar_name share
        one bar (give them the same clim). clim: the colour range, fixed across an animation;
        None takes the range of the scalars given here.
        Without scalars the body gets `color`, or the next of BODY_COLORS.
        """
        if name in self._bodies:
            raise TissueError(f"render: a body named {name!r} is already in the scene")
        mesh = _triangles(points, faces, f"body {name!r}")
        color = color or BODY_COLORS[len(self._bodies) % len(BODY_COLORS)]
        edges = self.edges if edges is None else edges
        kwargs = dict(color=color)
        if scalars is not None:
            scalar_name = scalar_name or "value"
            self._set_scalars(mesh, scalars, scalar_name, name)
            values = np.asarray(scalars, dtype=float)
            if clim is None:
                lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
                clim = (lo, hi if hi > lo else lo + 1.0)
            kwargs = dict(scalars=scalar_name, cmap=cmap, clim=clim,
                          show_scalar_bar=scalar_name not in self._bars,
                          scalar_bar_args=self._bar_style(scalar_name, clim))
        actor = self.plotter.add_mesh(
            # Normals are split only at edges sharper than 60 degrees: a box stays a box, while a
            # coarse organ surface (dihedral angles well below that) still shades smoothly.
            mesh, name=f"body:{name}", smooth_shading=smooth, split_sharp_edges=smooth,
            feature_angle=60.0, show_edges=edges, edge_color=EDGE_COLOR,
            line_width=max(1.0, self.size[1] / 960), opacity=opacity, specular=0.25, specular_power=20,
            diffuse=0.9, ambient=0.12, **kwargs)
        if scalars is not None and scalar_name not in self._bars:
            bar = self.plotter.scalar_bars[scalar_name]
            bar.SetVerticalTitleSeparation(round(self.font_size * 0.8))  # title clear of top label
            bar.SetTextPad(round(self.font_size * 0.3))
            self._bars.add(scalar_name)
        self._bodies[name] = _Item(mesh, actor, scalar_name if scalars is not None else None)

    @property
    def bodies(self) -> list[str]:
        return list(self._bodies)

    def update_body(self, name: str, points=None, scalars=None, faces=None) -> None:
        """New points (same count, unless new `faces` come with them: a cut body) and/or scalars
        for a body; the camera does not move."""
        item = self._item(self._bodies, name, "body")
        if faces is not None:
            item.mesh.copy_from(_triangles(points, faces, f"body {name!r}"))
            item.reshaped = True
        elif points is not None:
            item.mesh.points = _same_shape(points, item.mesh, f"body {name!r}")
        if scalars is not None:
            if item.scalar_name is None:
                raise TissueError(f"render: body {name!r} was added without scalars")
            self._set_scalars(item.mesh, scalars, item.scalar_name, name)
        item.mesh.Modified()

    def add_obstacle(self, name: str, surface, *, color=None, opacity: float = 1.0,
                     edges: bool = False, smooth: bool = True, framed: bool = True, lit: bool = True) -> None:
        """A rigid obstacle: a pyvista surface (Plane, Sphere, Capsule, a read mesh ...) or a
        (points, faces) pair. framed=False leaves it out of the camera framing (large floors).
        lit=False draws it in one flat tone, like the ground (a large plane seen at a grazing
        angle would otherwise turn into a dark slab)."""
        if name in self._obstacles:
            raise TissueError(f"render: an obstacle named {name!r} is already in the scene")
        mesh = _surface(surface, f"obstacle {name!r}")
        # Sharp edges stay sharp (a box, a blade); curved faces are smooth.
        shading = dict(specular=0.4, specular_power=30, diffuse=0.85, ambient=0.12) if lit else dict(lighting=False)
        actor = self.plotter.add_mesh(
            mesh, name=f"obstacle:{name}", color=color or OBSTACLE_COLOR, opacity=opacity,
            smooth_shading=smooth, split_sharp_edges=smooth, show_edges=edges, edge_color=EDGE_COLOR, **shading)
        self._obstacles[name] = _Item(mesh, actor, framed=framed)

    def update_obstacle(self, name: str, points=None, transform=None) -> None:
        """Move an obstacle: new points (same topology) or a 4x4 rigid transform of its original pose."""
        item = self._item(self._obstacles, name, "obstacle")
        if points is not None:
            item.mesh.points = _same_shape(points, item.mesh, f"obstacle {name!r}")
            item.mesh.Modified()
        if transform is not None:
            item.actor.user_matrix = np.asarray(transform, dtype=float)

    def remove(self, name: str) -> None:
        """Take a body or obstacle out of the scene."""
        for kind, items in (("body", self._bodies), ("obstacle", self._obstacles)):
            if name in items:
                self.plotter.remove_actor(f"{kind}:{name}")
                self.plotter.remove_actor(f"shadow:{kind}:{name}")
                del items[name]
                return
        raise TissueError(f"render: nothing named {name!r} in the scene")

    def set_title(self, text: str | None) -> None:
        """A title at the top of every frame (None removes it)."""
        margin = round(self.size[1] / 40)
        self._text(text, (self.size[0] // 2, self.size[1] - margin), "title",
                   round(self.font_size * 1.3), centred=True)

    def set_label(self, text: str | None) -> None:
        """A small label in the lower-left corner, e.g. the simulated time (None removes it)."""
        margin = round(self.size[1] / 40)
        self._text(text, (margin, margin), "label", round(self.font_size * 0.9))

    def set_camera(self, preset=None, bounds=None, zoom: float | None = None) -> None:
        """Re-frame the camera now: a new preset, and/or bounds (default: the scene's current bounds)."""
        if preset is not None:
            self.camera = preset
        if zoom is not None:
            self.zoom = zoom
        if bounds is not None:
            self._bounds = tuple(float(b) for b in bounds)
        self._fix_camera(self._bounds or self.scene_bounds())

    def scene_bounds(self) -> tuple:
        """(xmin, xmax, ymin, ymax, zmin, zmax) over bodies and framed obstacles."""
        boxes = [np.array(i.actor.GetBounds()) for i in self._bodies.values()]
        boxes += [np.array(i.actor.GetBounds()) for i in self._obstacles.values() if i.framed]
        if not boxes:
            raise TissueError("render: the scene is empty; add a body or an obstacle first")
        b = np.array(boxes).reshape(-1, 3, 2)
        return tuple(np.stack([b[:, :, 0].min(0), b[:, :, 1].max(0)], axis=1).ravel())

    # ---- output --------------------------------------------------------------------------------

    def image(self) -> np.ndarray:
        """Render the current state: (h, w, 3) uint8, or (h, w, 4) with a transparent background."""
        if not self._camera_fixed:
            self._fix_camera(self._bounds or self.scene_bounds())
        if self.ground:
            self._update_shadows()
        self.plotter.renderer.reset_camera_clipping_range()  # bodies move; keep them all in depth
        self.plotter.render()  # pyvista's screenshot renders only the first time
        return np.asarray(self.plotter.screenshot(None, transparent_background=self.transparent,
                                                  return_img=True))

    def screenshot(self, path) -> Path:
        """Render the current state to a PNG file."""
        return write_png(path, self.image())

    def animation(self, *paths, fps: float = 20.0, gif_width: int | None = 480,
                  max_gif_frames: int = 120) -> "Animation":
        """An animation writing to one or more .gif / .mp4 files; call write_frame() per frame."""
        if not paths:
            raise TissueError("render: animation needs at least one .gif or .mp4 path")
        writers = [writer_for(p, fps, width=gif_width, max_frames=max_gif_frames)
                   if str(p).lower().endswith(".gif") else writer_for(p, fps) for p in paths]
        return Animation(self, writers)

    def close(self) -> None:
        self.plotter.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- internals -----------------------------------------------------------------------------

    def _item(self, items, name, kind) -> _Item:
        if name not in items:
            raise TissueError(f"render: no {kind} named {name!r}; known: {sorted(items)}")
        return items[name]

    @staticmethod
    def _set_scalars(mesh: pv.PolyData, scalars, scalar_name: str, body: str) -> None:
        values = np.asarray(scalars, dtype=float)
        if values.ndim != 1:
            raise TissueError(f"render: body {body!r}: scalars must be 1-D, got shape {values.shape}")
        if len(values) == mesh.n_points:
            mesh.point_data[scalar_name] = values
        elif len(values) == mesh.n_cells:
            mesh.cell_data[scalar_name] = values
        else:
            raise TissueError(f"render: body {body!r}: {len(values)} scalars match neither its "
                              f"{mesh.n_points} points nor its {mesh.n_cells} triangles")

    def _bar_style(self, title: str, clim) -> dict:
        # A vertical bar on the right, black text, few round labels: reads well in print.
        return dict(title=title, vertical=True, position_x=0.85, position_y=0.2, width=0.045,
                    height=0.55, n_labels=_label_count(*clim), fmt="%.3g", color="black", font_family="arial",
                    title_font_size=round(self.font_size * 1.15), label_font_size=self.font_size,
                    shadow=False, bold=False, unconstrained_font_size=True)

    def _text(self, text, position, name, size, centred=False) -> None:
        # render=False: each text change would otherwise cost two full renders (a GIF frame's label).
        self.plotter.remove_actor(name, render=False)
        if text:
            # Pixel positions (not pyvista's corner annotations, whose size follows the window).
            actor = self.plotter.add_text(text, position=position, font_size=size, color="black",
                                          font="arial", name=name, render=False)
            if centred:
                actor.prop.justification_horizontal = "center"
                actor.prop.justification_vertical = "top"

    def _fix_camera(self, bounds) -> None:
        b = np.array(bounds, dtype=float)
        if self.ground:
            self._add_ground(b)
        # With a colour bar the scene is framed in the image's left part, beside the bar rather
        # than under it: a narrower frame, shifted left (window centre is in units of half-widths).
        width = BAR_FREE_WIDTH if self._bars else 1.0
        position = camera_position(b, self.camera, self.up, aspect=width * self.size[0] / self.size[1],
                                   view_angle=self.plotter.camera.view_angle)
        self.plotter.camera_position = position
        self.plotter.camera.SetWindowCenter(1.0 - width, 0.0)
        if self.zoom != 1.0:
            self.plotter.camera.zoom(self.zoom)
        self._camera_fixed = True

    def _add_ground(self, bounds) -> None:
        """A floor just below the framed bounds, three times their footprint; added once."""
        if self._ground_height is not None:
            return
        b = bounds.reshape(3, 2)
        centre, extent = b.mean(1), b[:, 1] - b[:, 0]
        size = 3.0 * max(np.linalg.norm(extent - (extent @ self.up) * self.up), 1e-6)
        corners = np.array(np.meshgrid(*b, indexing="ij")).reshape(3, -1).T
        self._ground_height = (corners @ self.up).min() - 0.005 * np.linalg.norm(extent)
        self._shadow_lift = 1e-3 * np.linalg.norm(extent)  # above the floor, no z-fighting
        origin = centre - (centre @ self.up - self._ground_height) * self.up
        plane = pv.Plane(center=origin, direction=self.up, i_size=size, j_size=size)
        # Unlit floor and shadows: flat tones like a drawn figure, the same in every frame.
        self.plotter.add_mesh(plane, name="ground", color=GROUND_COLOR, lighting=False)

    def _update_shadows(self) -> None:
        """Project every body and obstacle straight down onto the floor (one flat, opaque colour,
        so overlapping layers of the flattened surface do not darken each other)."""
        for kind, items in (("body", self._bodies), ("obstacle", self._obstacles)):
            for name, item in items.items():
                m = np.asarray(item.actor.user_matrix)
                world = item.mesh.points @ m[:3, :3].T + m[:3, 3]
                height = world @ self.up - (self._ground_height + self._shadow_lift)
                flat = world - np.outer(height, self.up)
                if item.shadow is None:
                    item.shadow = pv.PolyData(flat, item.mesh.faces)
                    self.plotter.add_mesh(item.shadow, name=f"shadow:{kind}:{name}",
                                          color=SHADOW_COLOR, lighting=False)
                elif item.reshaped:
                    item.shadow.copy_from(pv.PolyData(flat, item.mesh.faces))
                    item.reshaped = False
                else:
                    item.shadow.points = flat
                    item.shadow.Modified()


class Animation:
    """Frames of one Renderer written to GIF/MP4 files; use as a context manager or call close()."""

    def __init__(self, renderer: Renderer, writers):
        self.renderer, self.writers = renderer, writers
        self.frames = 0

    def write_frame(self, label: str | None = None) -> None:
        """Render the renderer's current state (with an optional label, e.g. 't = 0.40 s')."""
        if label is not None:
            self.renderer.set_label(label)
        image = flatten(self.renderer.image())
        for w in self.writers:
            w.append(image)
        self.frames += 1

    def close(self) -> list[Path]:
        """Finish the files; returns the paths written (a skipped MP4 is left out)."""
        return [p for p in (w.close() for w in self.writers) if p is not None]

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _same_shape(points, mesh, what: str) -> np.ndarray:
    """New points for a drawn mesh, refused unless there is one per existing point."""
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (mesh.n_points, 3):
        raise TissueError(f"render: {what}: expected points of shape {(mesh.n_points, 3)}, got {points.shape}")
    return points
