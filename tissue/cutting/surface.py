"""The cut surface: what a blade sweeps between two steps, and the geometric queries cutting asks
of it (which mesh edges cross it and where, how far a point is from it, on which side).

A blade is a segment (a, b). Moving from (a₀, b₀) to (a₁, b₁) in one step it sweeps the bilinear
patch a₀ b₀ b₁ a₁, kept as the two triangles (a₀, b₀, b₁) and (a₀, b₁, a₁) (exact when the patch
is planar, as it is for a blade translated in its own plane). A predefined cut path (`CutPath`: a
polyline traced by one end of the blade, the blade pointing along a fixed depth direction) is a
sequence of such sweeps. A `CutSurface` accumulates every patch swept so far: an element is split
only once the whole surface crosses it, so a cut advances element by element behind the blade.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import TissueError


def sweep(blade_from, blade_to) -> np.ndarray:
    """(2, 3, 3) the triangles of the patch a blade (2, 3) sweeps from one pose to the next."""
    (a0, b0), (a1, b1) = np.asarray(blade_from, np.float64), np.asarray(blade_to, np.float64)
    return np.array([[a0, b0, b1], [a0, b1, a1]])


@dataclass(frozen=True)
class CutPath:
    """A predefined cut: the blade's top end follows `points` (a polyline, k × 3) at arc length s,
    the blade reaching `depth` metres along the unit `direction` from it."""

    points: np.ndarray
    direction: np.ndarray
    depth: float

    def __post_init__(self):
        points = np.asarray(self.points, np.float64).reshape(-1, 3)
        direction = np.asarray(self.direction, np.float64).reshape(3)
        if len(points) < 2 or not np.isfinite(points).all():
            raise TissueError(f"cut path: needs at least 2 finite points, got {len(points)}")
        if not np.linalg.norm(direction) > 0 or not self.depth > 0:
            raise TissueError(f"cut path: the depth direction {direction.tolist()} and depth {self.depth} must be "
                              "non-zero")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "direction", direction / np.linalg.norm(direction))

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def blade(self, s: float) -> np.ndarray:
        """(2, 3) the blade when its top end has travelled s metres along the path (clamped)."""
        lengths = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        ends = np.cumsum(lengths)
        s = float(np.clip(s, 0.0, ends[-1]))
        k = min(int(np.searchsorted(ends, s)), len(lengths) - 1)
        f = (s - (ends[k] - lengths[k])) / lengths[k]
        top = (1.0 - f) * self.points[k] + f * self.points[k + 1]
        return np.array([top, top + self.depth * self.direction])

    def sweep(self, s0: float, s1: float) -> np.ndarray:
        """(2 k, 3, 3) the triangles swept from arc length s0 to s1 (one patch per polyline piece
        crossed, so a bend is followed exactly)."""
        ends = np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))
        stations = np.unique(np.r_[s0, ends[(ends > s0) & (ends < s1)], s1])
        return np.concatenate([sweep(self.blade(a), self.blade(b)) for a, b in zip(stations[:-1], stations[1:])])


class CutSurface:
    """The triangles swept so far (k, 3, 3), with their unit normals."""

    def __init__(self):
        self.triangles = np.zeros((0, 3, 3))
        self.normals = np.zeros((0, 3))
        self._edges = np.zeros((0, 3, 3))           # per triangle, edge i: corner i+1 − corner i
        self._inward = np.zeros((0, 3, 3))          # normal × edge: points inside have (p − a)·it ≥ 0

    def add(self, triangles) -> None:
        """Add swept triangles; degenerate ones (the blade did not move) are dropped."""
        t = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        area = np.linalg.norm(n, axis=1)
        keep = area > 1e-12 * max(float(np.ptp(t.reshape(-1, 3), axis=0).max(initial=0.0)) ** 2, 1e-300)
        t, n = t[keep], n[keep] / area[keep, None]
        edges = t[:, [1, 2, 0]] - t
        self.triangles = np.concatenate([self.triangles, t])
        self.normals = np.concatenate([self.normals, n])
        self._edges = np.concatenate([self._edges, edges])
        self._inward = np.concatenate([self._inward, np.cross(n[:, None, :], edges)])

    def __len__(self) -> int:
        return len(self.triangles)

    def near(self, lo, hi) -> np.ndarray:
        """Ids of the triangles whose bounding box meets the box [lo, hi]."""
        t = self.triangles
        return np.flatnonzero((t.min(axis=1) <= hi).all(axis=1) & (t.max(axis=1) >= lo).all(axis=1))

    def crossings(self, a: np.ndarray, b: np.ndarray, triangles=None) -> tuple[np.ndarray, np.ndarray]:
        """Where segments a→b (k, 3) cross the surface: (t (k,), triangle (k,)) with t ∈ (0, 1) the
        fraction from a of the first crossing, NaN (triangle −1) where none. Möller–Trumbore,
        one segment against every given triangle (default: all)."""
        ids = np.arange(len(self)) if triangles is None else np.asarray(triangles)
        k = len(a)
        t_out, tri_out = np.full(k, np.nan), np.full(k, -1)
        if k == 0 or len(ids) == 0:
            return t_out, tri_out
        T = self.triangles[ids].transpose(1, 2, 0)[:, :, None, :]          # (corner, 3, 1, m)
        p0, e1, e2 = T[0], T[1] - T[0], T[2] - T[0]
        d = (b - a).T[:, :, None]                                          # (3, k, 1)
        h = _cross(d, e2)                                                  # (3, k, m)
        det = _dot(h, e1)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = a.T[:, :, None] - p0
        u = _dot(s, h) * inv
        q = _cross(s, e1)
        v = _dot(d, q) * inv
        t = _dot(e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < 1)
        t = np.where(hit, t, np.inf)
        first = np.argmin(t, axis=1)
        best = t[np.arange(k), first]
        found = np.isfinite(best)
        t_out[found], tri_out[found] = best[found], ids[first[found]]
        return t_out, tri_out

    def distances(self, points: np.ndarray, triangles=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distance (k,), side (k,) ±1, nearest triangle (k,)) of points to the nearest given
        triangle (default: all), the side that of the nearest triangle's plane (+ along its normal)."""
        ids = np.arange(len(self)) if triangles is None else np.asarray(triangles)
        if len(ids) == 0:
            return np.full(len(points), np.inf), np.ones(len(points)), np.full(len(points), -1)
        # Coordinates first, (3, points, triangles): sums over a last axis of 3 cost many times more.
        corners = self.triangles[ids].transpose(1, 2, 0)[:, :, None, :]     # (corner, 3, 1, m)
        edges = self._edges[ids].transpose(1, 2, 0)[:, :, None, :]
        inward = self._inward[ids].transpose(1, 2, 0)[:, :, None, :]
        p = points.T[:, :, None]                                           # (3, k, 1)
        plane = _dot(p - corners[0], self.normals[ids].T[:, None, :])      # (k, m)
        inside = np.ones(plane.shape, bool)
        distance = np.full(plane.shape, np.inf)
        for i in range(3):                  # the foot on the plane left of every edge, else the
            pa, ab = p - corners[i], edges[i]                  # nearest point of an edge
            inside &= _dot(pa, inward[i]) >= 0                 # (the foot's offset is along n)
            off = pa - np.clip(_dot(pa, ab) / _dot(ab, ab), 0.0, 1.0) * ab
            distance = np.minimum(distance, np.sqrt(_dot(off, off)))
        distance = np.minimum(distance, np.where(inside, np.abs(plane), np.inf))
        nearest = np.argmin(distance, axis=1)
        rows = np.arange(len(points))
        return distance[rows, nearest], np.where(plane[rows, nearest] >= 0, 1.0, -1.0), ids[nearest]


    def distances_near(self, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As distances(points), against the triangles whose boxes come within `reach` of the
        points' box: exact for the points found within `reach` (a nearer triangle would be among
        them), the others measured again against all."""
        distance, side, nearest = self.distances(points, self.near(points.min(axis=0) - reach,
                                                                   points.max(axis=0) + reach))
        far = distance > reach
        if far.any():
            distance[far], side[far], nearest[far] = self.distances(points[far])
        return distance, side, nearest


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Σ over the first axis (3 coordinates) of u v."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u × v over the first axis (3 coordinates), broadcasting the others."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])
