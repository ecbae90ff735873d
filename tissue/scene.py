"""Scenes as dataclasses, and the Simulation that builds only what a scene declares.

A scene is a dataclass of plain typed fields (`Scene` subclass, one per module in `scenes/`):

    @dataclass
    class Liver(Scene):
        \"\"\"A liver held at three small patches near its top, swinging under gravity.\"\"\"
        dt: float = 0.02
        liver: SoftBody = field(default_factory=lambda: SoftBody(
            mesh="liver", young=3000, poisson=0.3,
            fixed=Fixed(region=(0.35, 0.65, 0.3, 0.7, 0.9, 1.0), count=3, radius=0.012)))

Every field of type `SoftBody` is a soft body, named by its field (`liver`), so
`--set liver.young=5e3` reaches it. `Scene` itself holds what all scenes share: `dt`, `duration`,
`gravity`, `solver` (a `Solver`) and `render` (a `Render`). `validate(scene)` (run by `Simulation`)
checks every field's type and range and fails with one line naming the field; unknown keywords are
refused when a group is constructed (see `tissue.options`).

Simulation(scene, arch=None, precision=None)
    initialises the backend (`tissue.backend.init`), builds each soft body (mesh, `CorotationalFEM`,
    `ImplicitEuler`, its held nodes and boundary triangles) and then the stages of a step, from the
    list `STAGES`. `.step()` runs the stages in order, timing each in `.stats` (a `tissue.stats.Stats`:
    per-stage wall time and counters, the bodies' own stages merged in as "stage: sub-stage");
    `.run(steps, progress=..., callback=...)`; `.state()` gives numpy arrays for output. The one-off
    costs are apart: `.mesh_seconds` (building the meshes) and `.compiled()` (kernel compilation
    since the simulation began; `.compile_seconds_by_step`: its share in each step).

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

import time
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Callable, Literal, Protocol

import numpy as np

from . import backend, compilation
from .errors import TissueError
from .mesh.closed_surface import SURFACE_SUFFIXES
from .mesh.organs import ORGANS as ORGAN_SURFACES
from .options import Options, apply_overrides, require, suggestion, validate
from .solver.implicit_euler import CGSettings, StepParameters
from .stats import Stats

__all__ = ["Fixed", "SoftBody", "Solver", "Render", "Scene", "Simulation", "Body", "Drawable", "STAGES",
           "add_stage", "validate", "apply_overrides", "build_mesh", "held_nodes"]

ORGANS = tuple(ORGAN_SURFACES)
SHAPES = ("beam", "box")
OUTPUTS = ("png", "gif", "mp4", "vtu")


# ---- the option groups ---------------------------------------------------------------------------


@dataclass
class Fixed(Options):
    """The nodes of a body held in place (zero velocity): the union of a region and explicit ids.

    region  a box given in fractions of the body's own rest bounding box (before its pose):
            (x0, x1, y0, y1, z0, z1), 0 = the minimum, 1 = the maximum along that axis. The x = min
            face is (0, 0, 0, 1, 0, 1); the top tenth is (0, 1, 0, 1, 0.9, 1). Empty: no region.
    count   hold only this many nodes of the region, spread over it: the node nearest the region's
            centre first, then each time the node farthest from those already chosen. 0: all.
    radius  with count: also hold every node within this distance (m) of a chosen node, so each
            hold is a small patch rather than one node (a point load pulls a cone out of soft tissue).
    nodes   explicit node ids of the body's mesh (in its file's or generator's numbering).
    """

    region: tuple[float, ...] = ()
    count: int = 0
    radius: float = 0.0
    nodes: tuple[int, ...] = ()

    @classmethod
    def end(cls, side: str = "-x", fraction: float = 0.0, count: int = 0) -> "Fixed":
        """The nodes within `fraction` of the body's extent from one end: side '-x' (x minimum),
        '+x', '-y', '+y', '-z' (bottom) or '+z' (top)."""
        if len(side) != 2 or side[0] not in "+-" or side[1] not in "xyz":
            raise TissueError(f"Fixed.end: side must be one of -x, +x, -y, +y, -z, +z, got {side!r}")
        region = [0.0, 1.0] * 3
        axis = "xyz".index(side[1])
        region[2 * axis: 2 * axis + 2] = [0.0, fraction] if side[0] == "-" else [1.0 - fraction, 1.0]
        return cls(region=tuple(region), count=count)

    def check(self):
        require(len(self.region) in (0, 6), "region",
                f"expected 6 fractions (x0, x1, y0, y1, z0, z1) or none, got {len(self.region)} values")
        if len(self.region) == 6:
            for axis in range(3):
                lo, hi = self.region[2 * axis], self.region[2 * axis + 1]
                require(lo <= hi, "region", f"{'xyz'[axis]}: the lower fraction {lo} exceeds the upper {hi}")
        require(self.count >= 0, "count", f"must be >= 0, got {self.count}")
        require(self.count == 0 or len(self.region) == 6, "count", "counts nodes of a region; give a region too")
        require(self.radius >= 0, "radius", f"must be >= 0 m, got {self.radius}")
        require(self.radius == 0 or self.count > 0, "radius", "grows the holds chosen by count; give a count too")
        bad = [n for n in self.nodes if n < 0]
        require(not bad, "nodes", f"node ids must be >= 0, got {bad[:5]}")


@dataclass
class SoftBody(Options):
    """A deformable body: where its mesh comes from, its material, held nodes and initial pose.

    mesh: 'liver', 'stomach' or 'colon' (procedural organs, `tissue.mesh.organs`, filled with about
    `tets` tetrahedra); 'beam' (x from 0 to size[0], section centred on the x axis) or 'box'
    (centred on the origin), gridded by `cells` (6 tetrahedra per cell); or a file path: a volume
    mesh in any format `tissue.mesh.read_mesh` reads (.vtu, .vtk, .msh, legacy Gmsh, ...), or a
    closed surface (.obj, .stl, .ply, .off) filled with about `tets` tetrahedra on load.
    The pose (applied after `scale`): rotate by `orientation` (degrees about the world x, then y,
    then z axis, around the mesh's origin), then translate by `position` (m).
    """

    mesh: str = "liver"
    tets: int = 1300
    size: tuple[float, float, float] = (1.0, 0.1, 0.1)
    cells: tuple[int, int, int] = (20, 2, 2)
    scale: float = 1.0
    young: float = 3000.0       # Pa
    poisson: float = 0.3
    density: float = 1000.0     # kg/m^3
    # co-rotational method: 'polar' stays bounded where 'large' gains energy (ν ≥ 0.45, soft
    # materials: bench/stability.py); 'invertible' adds a compression limit that un-inverts
    # elements; 'large' is SOFA's default and a little cheaper
    rotation: Literal["large", "polar", "invertible", "linear"] = "polar"
    fixed: Fixed = field(default_factory=Fixed)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)      # m
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)   # degrees about x, y, z

    def check(self):
        kind = mesh_kind(self.mesh)
        if kind == "file":
            path = Path(self.mesh)
            if not path.exists() and not path.suffix:  # a name rather than a path
                hint = suggestion(self.mesh, ORGANS + SHAPES)
                require(False, "mesh", f"{self.mesh!r} is neither a built-in mesh ({', '.join(ORGANS + SHAPES)}) "
                        f"nor an existing file{hint if 'did you mean' in hint else ''}")
            require(path.exists(), "mesh", f"no such file {str(path)!r}")
            require(path.is_file(), "mesh", f"not a file {str(path)!r}")
        if kind in ("organ", "surface"):
            require(8 <= self.tets <= 3_000_000, "tets", f"must lie in [8, 3000000], got {self.tets}")
        if kind == "shape":
            require(all(s > 0 for s in self.size), "size", f"lengths must be > 0 m, got {self.size}")
            require(all(c >= 1 for c in self.cells), "cells", f"cell counts must be >= 1, got {self.cells}")
        require(self.scale > 0, "scale", f"must be > 0, got {self.scale}")
        require(self.young > 0, "young", f"Young's modulus must be > 0 Pa, got {self.young}")
        require(-1.0 < self.poisson < 0.5, "poisson",
                f"Poisson's ratio must lie in (-1, 0.5), got {self.poisson} "
                "(0.5 is incompressible, which linear tetrahedra cannot represent)")
        require(self.density > 0, "density", f"must be > 0 kg/m^3, got {self.density}")


@dataclass
class Solver(Options):
    """Implicit Euler solved by CG (`tissue.solver.ImplicitEuler`), shared by all bodies.

    operator: 'assembled' forms Σ R Kₑ Rᵀ in block rows once per step; 'matrix_free' recomputes
    it element by element in every CG iteration, as the paper does."""

    cg_iterations: int = CGSettings.max_iterations
    cg_tolerance: float = CGSettings.tolerance
    preconditioner: Literal["none", "jacobi", "multigrid"] = CGSettings.preconditioner
    rayleigh_mass: float = 0.1          # damping: alpha_M (1/s)
    rayleigh_stiffness: float = 0.1     # damping: alpha_K (s)
    accumulation: Literal["gather", "atomic"] = "gather"
    execution: Literal["auto", "serial", "parallel"] = "auto"
    operator: Literal["assembled", "matrix_free"] = "assembled"
    # 'energy': a step that raised the energy (kinetic + elastic less the work of gravity and the
    # applied forces) is redone as two half steps (tissue.solver.step_control): bounded where one
    # linearisation per step overshoots (soft material, large dt, impacts); 'none': every step once
    step_control: Literal["energy", "none"] = "energy"

    def check(self):
        require(self.cg_iterations >= 1, "cg_iterations", f"must be >= 1, got {self.cg_iterations}")
        require(self.cg_tolerance >= 0, "cg_tolerance", f"must be >= 0, got {self.cg_tolerance}")
        require(self.rayleigh_mass >= 0, "rayleigh_mass", f"must be >= 0, got {self.rayleigh_mass}")
        require(self.rayleigh_stiffness >= 0, "rayleigh_stiffness", f"must be >= 0, got {self.rayleigh_stiffness}")

    def parameters(self, scene: "Scene") -> StepParameters:
        """The step parameters of the scene's bodies: what a live solver can change."""
        return StepParameters(dt=scene.dt, gravity=tuple(scene.gravity), rayleigh_mass=self.rayleigh_mass,
                              rayleigh_stiffness=self.rayleigh_stiffness,
                              cg=CGSettings(max_iterations=self.cg_iterations, tolerance=self.cg_tolerance,
                                            preconditioner=self.preconditioner))


@dataclass
class Render(Options):
    """What a run writes under its output folder (see `tissue.output`)."""

    every: int = 2                                  # a GIF/MP4 frame and a VTU file every N steps
    size: tuple[int, int] = (1280, 960)             # PNG stills and figure.png, in pixels
    animation_size: tuple[int, int] = (640, 480)    # GIF/MP4 frames, in pixels
    camera: Literal["iso", "front", "side", "top"] = "iso"   # presets of tissue.render.PRESETS
    zoom: float = 1.0
    scalars: Literal["displacement", "von_mises"] | None = "displacement"   # colouring, or none
    outputs: tuple[str, ...] = ("png", "gif", "vtu")   # any of png (stills, figure.png), gif, mp4, vtu
    stills: tuple[float, ...] = (0.0, 0.5, 1.0)     # PNG frames at these fractions of the run
    figure: float = 1.0                             # figure.png: the frame at this fraction of the run
    title: str = ""                                 # on every image; "" for none
    # 'surface': draw the smooth surface a mesh was made from (organs, surface files), carried by
    # the tetrahedra (SOFA's visual model); 'mesh': the tetrahedral mesh's boundary.
    visual: Literal["surface", "mesh"] = "surface"
    ghost: bool = False                             # the initial shape, faint, behind the bodies
    edges: bool = False                             # triangle edges on the bodies
    ground: bool = True                             # a floor with drop shadows
    fps: float = 0.0                                # animation frame rate; 0: real time

    def check(self):
        require(self.every >= 1, "every", f"must be >= 1 step, got {self.every}")
        require(all(s >= 16 for s in self.size), "size", f"must be at least 16 x 16 pixels, got {self.size}")
        require(all(s >= 16 for s in self.animation_size), "animation_size",
                f"must be at least 16 x 16 pixels, got {self.animation_size}")
        require(self.zoom > 0, "zoom", f"must be > 0, got {self.zoom}")
        for name in self.outputs:
            require(name in OUTPUTS, "outputs", f"unknown output {name!r}{suggestion(name, OUTPUTS)}")
        require(all(0.0 <= s <= 1.0 for s in self.stills), "stills",
                f"fractions of the run must lie in [0, 1], got {self.stills}")
        require(0.0 <= self.figure <= 1.0, "figure", f"must lie in [0, 1], got {self.figure}")
        require(self.fps >= 0, "fps", f"must be >= 0, got {self.fps}")


@dataclass
class Scene(Options):
    """A simulation set-up; subclasses add their bodies as fields (see the module docstring)."""

    dt: float = 0.02                                      # s
    duration: float = 4.0                                 # s; steps = duration / dt
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    solver: Solver = field(default_factory=Solver)
    render: Render = field(default_factory=Render)

    @property
    def steps(self) -> int:
        """Number of steps of a full run: duration / dt, rounded."""
        return max(1, round(self.duration / self.dt))

    def parts(self, kind: type) -> dict:
        """{field name: value} of the fields whose value is a `kind` (e.g. SoftBody), in order."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__
                if isinstance(getattr(self, name), kind)}

    def bodies(self) -> dict[str, SoftBody]:
        return self.parts(SoftBody)

    @classmethod
    def description(cls) -> str:
        """The first line of the class docstring."""
        doc = (cls.__doc__ or "").strip()
        if not doc or doc.startswith(cls.__name__ + "("):  # dataclass's generated signature
            return cls.__name__
        return doc.splitlines()[0].strip()

    def check(self):
        require(self.dt > 0, "dt", f"the time step must be > 0 s, got {self.dt}")
        require(self.duration > 0, "duration", f"must be > 0 s, got {self.duration}")
        require(self.bodies(), type(self).__name__, "declares no soft body (a field of type SoftBody)")

    def with_overrides(self, assignments) -> "Scene":
        """A copy with "a.b=value" assignments applied (see `tissue.options.apply_overrides`)."""
        return apply_overrides(self, assignments)


# ---- meshes and held nodes -----------------------------------------------------------------------


def mesh_kind(source: str) -> str:
    """'organ', 'shape', 'surface' (a closed surface file) or 'file' (a volume mesh file)."""
    if source in ORGANS:
        return "organ"
    if source in SHAPES:
        return "shape"
    if Path(source).suffix.lower() in SURFACE_SUFFIXES:
        return "surface"
    return "file"


@lru_cache(maxsize=16)
def _organ(name: str, tets: int):
    from .mesh.organs import organ_mesh

    return organ_mesh(name, target_tets=tets)


# Wall time this process has spent in build_mesh: a Simulation reports its share.
_mesh_seconds = 0.0


def build_mesh(body: SoftBody, name: str = "body"):
    """The body's TetMesh in its own frame (scaled, not yet posed)."""
    global _mesh_seconds
    start = time.perf_counter()
    try:
        return _make_mesh(body, name)
    finally:
        _mesh_seconds += time.perf_counter() - start


def _make_mesh(body: SoftBody, name: str):
    from .mesh import beam, box, read_mesh

    kind = mesh_kind(body.mesh)
    try:
        if kind == "organ":
            mesh = _organ(body.mesh, body.tets)
        elif body.mesh == "beam":
            mesh = beam(*body.size, body.cells[0], body.cells[1:])
        elif kind == "shape":
            mesh = box(size=body.size, cells=body.cells, origin=tuple(-0.5 * s for s in body.size))
        elif kind == "surface":
            from .mesh.closed_surface import read_surface
            from .mesh.tetrahedralize import tetrahedralize

            points, triangles = read_surface(body.mesh)
            mesh = tetrahedralize(points, triangles, target_tets=body.tets, source=body.mesh)
        else:
            mesh = read_mesh(body.mesh)
    except TissueError as err:
        raise TissueError(f"{name}.mesh: {err}") from None
    if body.scale != 1.0:
        mesh = mesh.transformed(scale=body.scale)
    return mesh


def source_surface(body: SoftBody):
    """(points, triangles) of the closed surface the body's mesh was made from, in its own frame
    (scaled, not posed); None for generated shapes and volume-mesh files."""
    kind = mesh_kind(body.mesh)
    if kind == "organ":
        from .mesh.organs import organ_surface

        points, triangles = organ_surface(body.mesh)
    elif kind == "surface":
        from .mesh.closed_surface import read_surface

        points, triangles = read_surface(body.mesh)
    else:
        return None
    return points * body.scale, triangles


def rotation_matrix(degrees) -> np.ndarray:
    """Rotation about the world x, then y, then z axis (angles in degrees): Rz Ry Rx."""
    ax, ay, az = np.radians(np.asarray(degrees, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def held_nodes(points: np.ndarray, fixed: Fixed, name: str = "body") -> np.ndarray:
    """The sorted node ids that `fixed` selects on a mesh with these (unposed) points."""
    chosen = [np.asarray(fixed.nodes, dtype=np.int64)]
    bad = chosen[0][chosen[0] >= len(points)]
    if len(bad):
        raise TissueError(f"{name}.fixed.nodes: ids {bad[:10].tolist()} out of range [0, {len(points)})")
    if len(fixed.region) == 6:
        lo, hi = points.min(axis=0), points.max(axis=0)
        u = (points - lo) / np.where(hi > lo, hi - lo, 1.0)
        r = np.asarray(fixed.region, dtype=np.float64).reshape(3, 2)
        eps = 1e-9
        inside = np.flatnonzero(np.all((u >= r[:, 0] - eps) & (u <= r[:, 1] + eps), axis=1))
        if len(inside) == 0:
            raise TissueError(f"{name}.fixed.region: {fixed.region} holds no node of the mesh "
                              f"({len(points)} nodes); widen it")
        if 0 < fixed.count < len(inside):
            inside = _spread(points[inside], inside, lo + r.mean(axis=1) * (hi - lo), fixed.count)
        if fixed.count > 0 and fixed.radius > 0:
            from scipy.spatial import cKDTree

            near = cKDTree(points).query_ball_point(points[inside], fixed.radius)
            inside = np.unique(np.concatenate([inside] + [np.asarray(n, dtype=np.int64) for n in near]))
        chosen.append(inside)
    return np.unique(np.concatenate(chosen)).astype(np.int64)


def _spread(points: np.ndarray, ids: np.ndarray, centre: np.ndarray, count: int) -> np.ndarray:
    """`count` of `ids` spread out: nearest the centre first, then farthest-point sampling."""
    first = int(np.argmin(np.linalg.norm(points - centre, axis=1)))
    picked = [first]
    distance = np.linalg.norm(points - points[first], axis=1)
    while len(picked) < count:
        nxt = int(np.argmax(distance))
        picked.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(points - points[nxt], axis=1))
    return ids[np.array(picked)]


# ---- the simulation ------------------------------------------------------------------------------


class Body:
    """One simulated soft body: its posed rest mesh, FEM, time integrator, held nodes, surface."""

    def __init__(self, name: str, spec: SoftBody, scene: Scene):
        from .fem import CorotationalFEM, Material
        from .mesh import boundary_faces
        from .solver import ImplicitEuler
        from .solver.step_control import EnergyControl

        self.name, self.spec = name, spec
        own = build_mesh(spec, name)
        self.fixed = held_nodes(own.points, spec.fixed, name)
        self.mesh = own.transformed(rotation=rotation_matrix(spec.orientation), translation=spec.position)
        self.faces = boundary_faces(self.mesh.tets)
        self.cut = np.zeros(len(self.faces), dtype=bool)     # boundary faces on a cut (drawn apart)
        self.topology = (self.mesh.points, self.faces, self.cut)   # what a recorded frame draws
        s = scene.solver
        try:
            material = Material(young=spec.young, poisson=spec.poisson, density=spec.density)
            self.fem = CorotationalFEM(self.mesh, material, rotation=spec.rotation, accumulation=s.accumulation)
            self.solver = ImplicitEuler.with_parameters(self.fem, s.parameters(scene), fixed=self.fixed,
                                                        execution=s.execution, operator=s.operator)
        except TissueError as err:
            raise TissueError(f"{name}: {err}") from None
        # What the free motion steps: the solver, or the solver with its energy check.
        self.stepper = EnergyControl(self.solver) if s.step_control == "energy" else self.solver
        self._visual = None

    def visual(self):
        """The body's smooth source surface embedded in its tetrahedra (`EmbeddedSurface`), or
        None when the mesh was not made from a surface (then draw `faces`)."""
        if self._visual is None:
            from .mesh.embedding import EmbeddedSurface

            surface = source_surface(self.spec)
            if surface is None:
                self._visual = False
            else:
                points = surface[0] @ rotation_matrix(self.spec.orientation).T + np.asarray(self.spec.position)
                self._visual = EmbeddedSurface(points, surface[1], self.mesh.points, self.mesh.tets)
        return self._visual or None

    def follow_model(self, cut=None) -> None:
        """After topology edits of the body's model (cutting): its rest mesh, boundary and held
        nodes as they are now, `cut` (a mask of the boundary faces) the faces on a cut; the smooth
        source surface is no longer drawn (it cannot show a cut)."""
        model = self.fem.model
        self.mesh = model.mesh()
        self.faces = model.boundary_faces()
        self.fixed = model.held_nodes
        self.cut = np.zeros(len(self.faces), dtype=bool) if cut is None else np.asarray(cut, dtype=bool)
        self.topology = (self.mesh.points, self.faces, self.cut)
        self._visual = False

    @property
    def rest(self) -> np.ndarray:
        return self.mesh.points

    def positions(self) -> np.ndarray:
        return self.solver.positions()

    def velocities(self) -> np.ndarray:
        return self.solver.velocities()

    def displacement(self) -> np.ndarray:
        return self.positions() - self.rest

    def element_stress(self) -> np.ndarray:
        """Co-rotational Cauchy-like stress R σ Rᵀ of each element (m, 3, 3), at the current positions."""
        return self.fem.element_stress_numpy(self.solver.x)

    def von_mises(self) -> np.ndarray:
        """Von Mises equivalent stress of each element (Pa)."""
        return von_mises(self.element_stress())

    def nodal(self, element_values: np.ndarray) -> np.ndarray:
        """Per-element values averaged to the nodes (weighted by element volume)."""
        tets, volumes = self.mesh.tets, self.mesh.volumes
        total = np.zeros(self.mesh.n_points)
        weight = np.zeros(self.mesh.n_points)
        np.add.at(total, tets.reshape(-1), np.repeat(element_values * volumes, 4))
        np.add.at(weight, tets.reshape(-1), np.repeat(volumes, 4))
        return total / np.maximum(weight, 1e-300)


def von_mises(stress: np.ndarray) -> np.ndarray:
    """sqrt(3/2 s:s) of symmetric stresses (..., 3, 3), s the deviatoric part."""
    trace = np.trace(stress, axis1=-2, axis2=-1)
    s = stress - trace[..., None, None] / 3.0 * np.eye(3)
    return np.sqrt(1.5 * np.sum(s * s, axis=(-2, -1)))


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
        meshes_before = _mesh_seconds
        self.bodies: dict[str, Body] = {name: Body(name, spec, scene) for name, spec in scene.bodies().items()}
        self.mesh_seconds = _mesh_seconds - meshes_before
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
        `rayleigh_mass`, `rayleigh_stiffness` (e.g. `sim.set_parameters(dt=0.01, cg_iterations=50)`).
        The contact stage's compliance is built for one step matrix, so with contact dt and
        damping stay as built."""
        scene_fields, solver_fields = {"dt", "gravity"}, {"cg_iterations", "cg_tolerance", "rayleigh_mass",
                                                          "rayleigh_stiffness"}
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
        `progress(done, steps)`."""
        steps = self.scene.steps if steps is None else int(steps)
        if steps < 0:
            raise TissueError(f"steps: must be >= 0, got {steps}")
        for i in range(steps):
            self.step()
            if callback is not None:
                callback(self)
            if progress is not None:
                progress(i + 1, steps)

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
