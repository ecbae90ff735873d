"""A scene's soft body made real: its mesh, held nodes and pose, FEM and time integrator.

`Body(name, spec, scene)` builds one `SoftBody` of a scene: the mesh (`build_mesh`: an organ, a
shape, a surface filled with tetrahedra or a volume-mesh file, scaled), the nodes it holds
(`held_nodes`), the pose (`rotation_matrix`), the `CorotationalFEM` and the `ImplicitEuler` that
steps it (with the energy check when the scene asks), and views of its state for output.
"""

from __future__ import annotations

import time
from functools import lru_cache

import numpy as np

from .errors import TissueError
from .scene import Fixed, Scene, SoftBody, mesh_kind

__all__ = ["Body", "build_mesh", "held_nodes", "mesh_seconds", "rotation_matrix", "source_surface", "von_mises"]



@lru_cache(maxsize=16)
def _organ(name: str, tets: int):
    from .mesh.organs import organ_mesh

    return organ_mesh(name, target_tets=tets)


# Wall time this process has spent in build_mesh: a Simulation reports its share.
_mesh_seconds = 0.0


def mesh_seconds() -> float:
    """Wall seconds this process has spent building meshes so far."""
    return _mesh_seconds


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
            # The nodes within `radius` of each of a few chosen ones, by their distances to each: a
            # k-d tree's answer, without importing scipy.spatial for it at every start.
            near = [np.flatnonzero(np.sum((points - points[i]) ** 2, axis=1) <= fixed.radius ** 2) for i in inside]
            inside = np.unique(np.concatenate([inside] + near))
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
        self.stepper = EnergyControl(self.solver, budget=s.energy_budget) if s.step_control == "energy" else self.solver
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
