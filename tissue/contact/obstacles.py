"""Rigid obstacles: primitives (plane, sphere, capsule, box) and closed triangle meshes, each
obstacle a union of shapes in its own frame, placed in the world by a pose that may follow a
prescribed motion (a function of time).

A pose is (R, t): world = R local + t. `motion(time)` may return a translation (3,), a pair
(R, t) or a 4×4 homogeneous matrix; without a motion the obstacle stays where its shapes are.
Rigid obstacles have no compliance: only their motion enters the constraints (through the
displacement of the touched material point during the step, for friction).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import TissueError

# Primitive codes and the packed row each primitive becomes for the detection kernel:
# [code, 15 parameters] in the obstacle's frame.
PLANE, SPHERE, CAPSULE, BOX = range(4)
PRIMITIVE_WIDTH = 16


def _vec(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise TissueError(f"{name}: expected three finite numbers, got {value!r}")
    return v


def _positive(value, name: str) -> float:
    if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
        raise TissueError(f"{name}: must be a finite number > 0, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Plane:
    """The half-space below the plane through `point` with outward `normal` (solid underneath)."""

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)

    def packed(self) -> np.ndarray:
        n = _vec(self.normal, "Plane.normal")
        if np.linalg.norm(n) == 0:
            raise TissueError("Plane.normal: must be non-zero")
        return np.r_[PLANE, _vec(self.point, "Plane.point"), n / np.linalg.norm(n), np.zeros(9)]


@dataclass(frozen=True)
class Sphere:
    centre: tuple = (0.0, 0.0, 0.0)
    radius: float = 0.01

    def packed(self) -> np.ndarray:
        return np.r_[SPHERE, _vec(self.centre, "Sphere.centre"), _positive(self.radius, "Sphere.radius"),
                     np.zeros(11)]


@dataclass(frozen=True)
class Capsule:
    """The points within `radius` of the segment [a, b] (a rib, an instrument shaft)."""

    a: tuple = (0.0, 0.0, 0.0)
    b: tuple = (0.1, 0.0, 0.0)
    radius: float = 0.01

    def packed(self) -> np.ndarray:
        return np.r_[CAPSULE, _vec(self.a, "Capsule.a"), _vec(self.b, "Capsule.b"),
                     _positive(self.radius, "Capsule.radius"), np.zeros(8)]


@dataclass(frozen=True)
class Box:
    """A box of half-extents `half` around `centre`, axes the columns of `rotation`."""

    centre: tuple = (0.0, 0.0, 0.0)
    half: tuple = (0.05, 0.05, 0.05)
    rotation: tuple | None = None

    def packed(self) -> np.ndarray:
        half = _vec(self.half, "Box.half")
        if np.any(half <= 0):
            raise TissueError(f"Box.half: half-extents must be > 0, got {self.half!r}")
        R = np.eye(3) if self.rotation is None else np.asarray(self.rotation, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9):
            raise TissueError("Box.rotation: must be a 3×3 rotation matrix")
        return np.r_[BOX, _vec(self.centre, "Box.centre"), half, R.reshape(-1)]


@dataclass(frozen=True)
class TriangleMesh:
    """A closed, outward-oriented triangle surface (queried with open3d)."""

    points: np.ndarray
    triangles: np.ndarray


PRIMITIVES = (Plane, Sphere, Capsule, Box)


def plane_axes(plane: Plane) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal vectors spanning the plane (with its unit normal, a right-handed frame)."""
    n = np.asarray(plane.normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    u = np.cross(n, np.eye(3)[np.argmin(np.abs(n))])
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _sphere_patch(rings: int, segments: int):
    """Unit-sphere points and triangles (poles at ±z) by latitude rings."""
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    p = np.stack(np.meshgrid(theta, phi, indexing="ij"), -1).reshape(-1, 2)
    pts = np.column_stack([np.sin(p[:, 0]) * np.cos(p[:, 1]), np.sin(p[:, 0]) * np.sin(p[:, 1]), np.cos(p[:, 0])])
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    tri = np.concatenate([np.stack([a, a + segments, b], -1).reshape(-1, 3),
                          np.stack([b, a + segments, b + segments], -1).reshape(-1, 3)])
    return pts, tri


def shape_surface(shape, size: float = 0.3, resolution: int = 16):
    """(points, triangles) of a shape for drawing, in the obstacle's frame; a plane is a square of
    side `size` around its point."""
    if isinstance(shape, TriangleMesh):
        return np.asarray(shape.points, dtype=np.float64), np.asarray(shape.triangles)
    if isinstance(shape, Box):
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        R = np.eye(3) if shape.rotation is None else np.asarray(shape.rotation, dtype=np.float64)
        quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
        tri = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
        return (corners * shape.half) @ R.T + shape.centre, tri
    if isinstance(shape, Plane):
        u, w = plane_axes(shape)
        c = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * size / 2
        return np.asarray(shape.point, dtype=np.float64) + c[:, :1] * u + c[:, 1:] * w, np.array([[0, 1, 2], [0, 2, 3]])
    pts, tri = _sphere_patch(resolution // 2, resolution)
    if isinstance(shape, Sphere):
        return shape.radius * pts + shape.centre, tri
    a, b = np.asarray(shape.a, dtype=np.float64), np.asarray(shape.b, dtype=np.float64)
    axis = b - a
    length = np.linalg.norm(axis)
    z = axis / length
    x = np.cross(z, np.eye(3)[np.argmin(np.abs(z))])
    x /= np.linalg.norm(x)
    frame = np.column_stack([x, np.cross(z, x), z])
    # The upper hemisphere slides to b: the rings at the equator stretch into the cylinder.
    local = shape.radius * pts + np.where(pts[:, 2:] > 1e-9, [0, 0, length], 0.0)
    return local @ frame.T + a, tri


def as_pose(value) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) from a translation (3,), a pair (R, t) or a 4×4 matrix."""
    if isinstance(value, tuple) and len(value) == 2:
        R, t = np.asarray(value[0], dtype=np.float64), np.asarray(value[1], dtype=np.float64)
    else:
        a = np.asarray(value, dtype=np.float64)
        if a.shape == (4, 4):
            R, t = a[:3, :3], a[:3, 3]
        elif a.shape == (3,):
            R, t = np.eye(3), a
        else:
            raise TissueError("motion: a pose is a translation (3,), a pair (R, t) or a 4×4 matrix; "
                              f"got shape {a.shape}")
    if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise TissueError("motion: the pose must be a finite 3×3 rotation and a translation (3,)")
    return R, t


class RigidObstacle:
    """A rigid body made of shapes (primitives and/or triangle meshes) in its own frame.

    friction: the Coulomb coefficient of contacts on it (None: the contact settings decide).
    motion: time (s) -> pose; None for a static obstacle.
    """

    def __init__(self, shapes, motion: Callable | None = None, friction: float | None = None,
                 name: str = "obstacle"):
        shapes = list(shapes) if isinstance(shapes, (list, tuple)) else [shapes]
        if not shapes:
            raise TissueError(f"{name}: an obstacle needs at least one shape")
        for s in shapes:
            if not isinstance(s, PRIMITIVES + (TriangleMesh,)):
                raise TissueError(f"{name}: unknown shape {type(s).__name__}; expected Plane, Sphere, Capsule, "
                                  "Box or TriangleMesh")
        if friction is not None and not (np.isfinite(friction) and friction >= 0):
            raise TissueError(f"{name}.friction: must be a finite number ≥ 0, got {friction!r}")
        self.name, self.motion, self.friction = name, motion, friction
        self.shapes = shapes
        self.primitives = np.array([s.packed() for s in shapes if isinstance(s, PRIMITIVES)]).reshape(
            -1, PRIMITIVE_WIDTH)
        self.meshes = [s for s in shapes if isinstance(s, TriangleMesh)]
        self._scenes = None
        self._rest = (np.eye(3), np.zeros(3))           # the static pose, read-only: pose() hands it out
        for a in self._rest:
            a.setflags(write=False)

    def surface(self, size: float = 0.3, resolution: int = 16):
        """(points, triangles) of all its shapes, in its own frame, for drawing."""
        points, triangles, offset = [], [], 0
        for shape in self.shapes:
            p, t = shape_surface(shape, size, resolution)
            points.append(p)
            triangles.append(np.asarray(t) + offset)
            offset += len(p)
        return np.concatenate(points), np.concatenate(triangles).astype(np.int64)

    def bounding_ball(self) -> np.ndarray:
        """(4,) a ball (centre, radius) around all its primitives, from a ball around each, in the
        obstacle's frame; radius -1 where unbounded (a plane) or empty (no primitive)."""
        balls = []
        for row in self.primitives:
            code, a = int(row[0]), row[1:4]
            if code == SPHERE:
                balls.append(np.r_[a, row[4]])
            elif code == CAPSULE:
                b = row[4:7]
                balls.append(np.r_[0.5 * (a + b), 0.5 * np.linalg.norm(b - a) + row[7]])
            elif code == BOX:
                balls.append(np.r_[a, np.linalg.norm(row[4:7])])
            else:
                balls.append(np.r_[0.0, 0.0, 0.0, -1.0])
        balls = np.array(balls).reshape(-1, 4)
        if not len(balls) or np.any(balls[:, 3] < 0):
            return np.r_[0.0, 0.0, 0.0, -1.0]
        centre = 0.5 * (balls[:, :3].min(axis=0) + balls[:, :3].max(axis=0))
        return np.r_[centre, np.max(np.linalg.norm(balls[:, :3] - centre, axis=1) + balls[:, 3])]

    def bounding_boxes(self) -> np.ndarray:
        """(P, 6) box (low corner, high corner) around each primitive, in the obstacle's frame;
        ±1e300 where unbounded (a plane)."""
        boxes = []
        for row in self.primitives:
            code, a = int(row[0]), row[1:4]
            if code == SPHERE:
                boxes.append(np.r_[a - row[4], a + row[4]])
            elif code == CAPSULE:
                b, r = row[4:7], row[7]
                boxes.append(np.r_[np.minimum(a, b) - r, np.maximum(a, b) + r])
            elif code == BOX:
                extent = np.abs(row[7:16].reshape(3, 3)) @ row[4:7]
                boxes.append(np.r_[a - extent, a + extent])
            else:
                boxes.append(np.r_[np.full(3, -1e300), np.full(3, 1e300)])
        return np.array(boxes).reshape(-1, 6)

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        if self.motion is None:
            return self._rest
        return as_pose(self.motion(float(time)))

    # ---- triangle meshes: closest points on the host (open3d, imported only when used) ----------

    def mesh_closest(self, points_local: np.ndarray):
        """(gap, normal, closest point) in the obstacle's frame for each query point: the nearest
        over its triangle meshes; inf where it has none."""
        k = len(points_local)
        gap, normal, closest = np.full(k, np.inf), np.zeros((k, 3)), np.zeros((k, 3))
        if not self.meshes or k == 0:
            return gap, normal, closest
        if self._scenes is None:
            import open3d as o3d

            self._scenes = []
            for m in self.meshes:
                # Query near the origin: open3d works in float32.
                offset = np.asarray(m.points, dtype=np.float64).mean(axis=0)
                tm = o3d.t.geometry.TriangleMesh()
                tm.vertex.positions = o3d.core.Tensor((np.asarray(m.points) - offset).astype(np.float32))
                tm.triangle.indices = o3d.core.Tensor(np.asarray(m.triangles, dtype=np.int32))
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(tm)
                self._scenes.append((scene, offset, o3d))
        for scene, offset, o3d in self._scenes:
            q = o3d.core.Tensor(np.ascontiguousarray(points_local - offset, dtype=np.float32))
            found = scene.compute_closest_points(q)
            c = found["points"].numpy().astype(np.float64) + offset
            face_n = found["primitive_normals"].numpy().astype(np.float64)
            d = points_local - c
            dist = np.linalg.norm(d, axis=1)
            # Inside or outside by ray parity (robust at sharp edges, where the closest face's
            # normal can point either way).
            sign = np.where(scene.compute_signed_distance(q).numpy() < 0, -1.0, 1.0)
            n = np.where(dist[:, None] > 1e-12, sign[:, None] * d / np.maximum(dist, 1e-300)[:, None], face_n)
            g = sign * dist
            better = g < gap
            gap[better], normal[better], closest[better] = g[better], n[better], c[better]
        return gap, normal, closest
