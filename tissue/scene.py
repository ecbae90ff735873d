"""Scenes as dataclasses: what a simulation is made of, checked before anything is built.

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
`gravity`, `solver` (a `Solver`) and `render` (a `Render`). `validate(scene)` (run by
`tissue.simulation.Simulation`) checks every field's type and range and fails with one line naming
the field; unknown keywords are refused when a group is constructed (see `tissue.options`).
A body's mesh, held nodes and pose are made from its `SoftBody` by `tissue.body`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .errors import TissueError
from .mesh.closed_surface import SURFACE_SUFFIXES
from .mesh.organs import ORGANS as ORGAN_SURFACES
from .options import Options, apply_overrides, require, suggestion, validate
from .solver.parameters import CGSettings, StepParameters

__all__ = ["Fixed", "SoftBody", "Solver", "Render", "Scene", "validate", "apply_overrides", "mesh_kind"]

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
    # CG from the last step's solution (scaled to dt) instead of zero, to the same stopping rule:
    # fewer iterations and closer to the converged trajectory on the floor scene and liver_press
    # (bench/free_motion.py). A bare CGSettings starts cold: a step there is a function of the
    # state alone, as the tests and the accuracy benchmarks compare it.
    cg_warm_start: bool = True
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
    # With step_control 'energy' (its energy is the check's): no step ends above its start's energy
    # plus the work the moving obstacles did on the body, beyond what the solvers' own error allows
    # and never by more than the largest such allowance over the run; the excess is projected out
    # (tissue.solver.energy_budget)
    energy_budget: bool = True

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
                                            preconditioner=self.preconditioner, warm_start=self.cg_warm_start))


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


def mesh_kind(source: str) -> str:
    """'organ', 'shape', 'surface' (a closed surface file) or 'file' (a volume mesh file)."""
    if source in ORGANS:
        return "organ"
    if source in SHAPES:
        return "shape"
    if Path(source).suffix.lower() in SURFACE_SUFFIXES:
        return "surface"
    return "file"
