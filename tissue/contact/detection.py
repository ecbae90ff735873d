"""Proximity detection: the contact points of each soft body's surface that lie within the
contact (alarm) distance of a rigid obstacle or of another soft body's surface.

Contact points ("samples") are fixed points of a body's surface triangles, p = Σ uⱼ x[nⱼ]: its
vertices, and optionally its edge midpoints and triangle centroids (`surface_samples`), which keep
obstacles thinner than the mesh spacing (a probe, a rib) from slipping between the vertices (the
paper samples the surfaces with Layered Depth Images for the same reason). A contact is a sample
p, the closest point c on the other surface, the unit normal n (from the other surface toward the
side where p belongs) and the gap g = n·(p - c) (negative when p has penetrated). For soft–soft
contacts c is a point of a triangle of the other body with barycentric weights w, so
g = n·(Σ uⱼ xⱼ - Σ wⱼ yⱼ) is linear in both bodies' nodes.

  soft–rigid  one thread per (sample, obstacle) pair in a Taichi kernel, the nearest of the
              obstacle's primitives in the obstacle's frame; triangle-mesh obstacles are queried
              on the host with open3d (closest point, and inside/outside by ray parity).
  soft–soft   broad phase: the other body's surface triangles, their boxes grown by the alarm
              distance, binned in a uniform grid (built each step with a sort in numpy); narrow
              phase: one thread per sample, exact point–triangle distance to the triangles of its
              cell (Ericson's Voronoi-region test). Inside/outside is the sign of (p - c) against
              the interpolated area-weighted vertex normal at c, which stays right at edges and
              corners where a face normal can point either way. Both directions are detected
              (samples of A against triangles of B and of B against A).

Detection reads the positions after the free motion. Results come back as numpy arrays, sorted by
(body, sample, kind, other), so runs are deterministic.
"""

from dataclasses import dataclass, fields

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from .obstacles import BOX, CAPSULE, PLANE, SPHERE

GRID_MAX_CELLS = 1 << 18   # the soft–soft grid grows its cells rather than exceed this
SAMPLINGS = ("vertices", "edges", "faces")


def surface_samples(faces: np.ndarray, sampling: str = "vertices") -> tuple[np.ndarray, np.ndarray]:
    """(nodes (s, 3) int32, weights (s, 3)) of a surface's contact points: its vertices (v, v, v;
    1, 0, 0), then for "edges" and "faces" its edge midpoints, then for "faces" its centroids."""
    if sampling not in SAMPLINGS:
        raise TissueError(f"sampling: unknown {sampling!r}; expected one of {SAMPLINGS}")
    v = np.unique(faces)
    nodes, weights = [np.repeat(v[:, None], 3, axis=1)], [np.tile([1.0, 0.0, 0.0], (len(v), 1))]
    if sampling in ("edges", "faces"):
        e = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
        nodes.append(e[:, [0, 1, 1]])
        weights.append(np.tile([0.5, 0.5, 0.0], (len(e), 1)))
    if sampling == "faces":
        nodes.append(faces)
        weights.append(np.full((len(faces), 3), 1.0 / 3.0))
    return np.concatenate(nodes).astype(np.int32), np.concatenate(weights)


@dataclass
class Contacts:
    """One row per contact point (all arrays have the same first dimension k)."""

    body: np.ndarray            # (k,) soft body the contact point belongs to
    sample: np.ndarray          # (k,) index of the point among that body's samples (its identity)
    nodes: np.ndarray           # (k, 3) the body's nodes carrying the point (a vertex: v, v, v)
    own_weights: np.ndarray     # (k, 3) its weights on them (a vertex: 1, 0, 0)
    other: np.ndarray           # (k,) obstacle index (rigid) or body index (soft)
    soft: np.ndarray            # (k,) bool: the other side is a soft body
    triangle: np.ndarray        # (k, 3) nodes of the other body's triangle (soft), else -1
    weights: np.ndarray         # (k, 3) barycentric weights of c on that triangle (soft), else 0
    normal: np.ndarray          # (k, 3) unit normal, from the other surface toward the point
    gap: np.ndarray             # (k,) signed distance along the normal (< 0: penetration)
    closest: np.ndarray         # (k, 3) the closest point c on the other surface
    other_motion: np.ndarray    # (k, 3) rigid: displacement of the material point at c over the step

    def __len__(self) -> int:
        return len(self.body)

    @property
    def vertex(self) -> np.ndarray:
        """The node of each contact point that is a vertex (the first carrier node otherwise)."""
        return self.nodes[:, 0]

    @staticmethod
    def empty() -> "Contacts":
        i, f = np.int32, float
        return Contacts(*(np.zeros(s, dtype=d) for s, d in (
            (0, i), (0, i), ((0, 3), i), ((0, 3), f), (0, i), (0, bool), ((0, 3), i), ((0, 3), f),
            ((0, 3), f), (0, f), ((0, 3), f), ((0, 3), f))))

    @staticmethod
    def concatenate(parts: list["Contacts"]) -> "Contacts":
        parts = [p for p in parts if len(p)]
        if not parts:
            return Contacts.empty()
        c = Contacts(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Contacts)))
        return c.take(np.lexsort((c.other, c.soft, c.sample, c.body)))

    def take(self, index) -> "Contacts":
        return Contacts(*(getattr(self, f.name)[index] for f in fields(Contacts)))

    def keys(self) -> np.ndarray:
        """An integer identity per contact (body, sample, kind, other), stable across steps."""
        return ((self.body.astype(np.int64) << 40) | (self.sample.astype(np.int64) << 12)
                | (self.soft.astype(np.int64) << 11) | self.other.astype(np.int64))


# --------------------------------------------------------------------------------------------
# soft–rigid: primitives in Taichi
# --------------------------------------------------------------------------------------------

@ti.func
def _p3(prm: ti.template(), k, i):
    return ti.Vector([prm[k, i], prm[k, i + 1], prm[k, i + 2]])


@ti.func
def _round_point(p, centre, radius):
    """Signed distance, normal and closest point of a ball (also the capsule around its axis)."""
    d = p - centre
    length = d.norm()
    n = ti.Vector([0.0, 0.0, 1.0])
    if length > 1e-300:
        n = d / length
    c = centre + radius * n
    return ti.Vector([length - radius, n[0], n[1], n[2], c[0], c[1], c[2]])


@ti.func
def _closest_primitive(prm: ti.template(), k, p):
    """[gap, normal (3), closest point (3)] of point p to primitive k (all in its frame)."""
    kind = ti.cast(prm[k, 0], ti.i32)
    out = ti.Vector([1e300, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    if kind == PLANE:
        o, n = _p3(prm, k, 1), _p3(prm, k, 4)
        g = (p - o).dot(n)
        c = p - g * n
        out = ti.Vector([g, n[0], n[1], n[2], c[0], c[1], c[2]])
    elif kind == SPHERE:
        out = _round_point(p, _p3(prm, k, 1), prm[k, 4])
    elif kind == CAPSULE:
        a, b = _p3(prm, k, 1), _p3(prm, k, 4)
        ab = b - a
        s = ti.min(ti.max((p - a).dot(ab) / ti.max(ab.dot(ab), 1e-300), 0.0), 1.0)
        out = _round_point(p, a + s * ab, prm[k, 7])
    elif kind == BOX:
        centre, half = _p3(prm, k, 1), _p3(prm, k, 4)
        R = ti.Matrix([[prm[k, 7], prm[k, 8], prm[k, 9]], [prm[k, 10], prm[k, 11], prm[k, 12]],
                       [prm[k, 13], prm[k, 14], prm[k, 15]]])
        q = R.transpose() @ (p - centre)
        excess = ti.abs(q) - half
        n, c, g = ti.Vector([0.0, 0.0, 1.0]), q, 0.0
        if excess.max() > 0.0:                      # outside: clamp onto the box
            c = ti.min(ti.max(q, -half), half)
            d = q - c
            g = d.norm()
            n = d / g
        else:                                       # inside: leave through the nearest face
            i = 0
            for j in ti.static(range(1, 3)):
                if excess[j] > excess[i]:
                    i = j
            side = 1.0 if q[i] >= 0.0 else -1.0
            n = ti.Vector([0.0, 0.0, 0.0])
            n[i] = side
            c[i] = side * half[i]
            g = excess[i]
        n, c = R @ n, R @ c + centre
        out = ti.Vector([g, n[0], n[1], n[2], c[0], c[1], c[2]])
    return out


@ti.func
def sample_position(x: ti.template(), nodes: ti.template(), weights: ti.template(), s):
    return weights[s, 0] * x[nodes[s, 0]] + weights[s, 1] * x[nodes[s, 1]] + weights[s, 2] * x[nodes[s, 2]]


@ti.kernel
def _rigid_kernel(x: ti.template(), nodes: ti.types.ndarray(), weights: ti.types.ndarray(),
                  prm: ti.types.ndarray(), offsets: ti.types.ndarray(), poses: ti.types.ndarray(),
                  out: ti.types.ndarray()):
    for s, o in ti.ndrange(nodes.shape[0], offsets.shape[0] - 1):
        R = ti.Matrix([[poses[o, 0], poses[o, 1], poses[o, 2]], [poses[o, 3], poses[o, 4], poses[o, 5]],
                       [poses[o, 6], poses[o, 7], poses[o, 8]]])
        t = ti.Vector([poses[o, 9], poses[o, 10], poses[o, 11]])
        p = R.transpose() @ (sample_position(x, nodes, weights, s) - t)
        best = ti.Vector([1e300, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        for k in range(offsets[o], offsets[o + 1]):
            r = _closest_primitive(prm, k, p)
            if r[0] < best[0]:
                best = r
        n = R @ ti.Vector([best[1], best[2], best[3]])
        c = R @ ti.Vector([best[4], best[5], best[6]]) + t
        out[s, o, 0] = best[0]
        for i in ti.static(range(3)):
            out[s, o, 1 + i] = n[i]
            out[s, o, 4 + i] = c[i]


# --------------------------------------------------------------------------------------------
# soft–soft: grid broad phase (numpy), point–triangle narrow phase (Taichi)
# --------------------------------------------------------------------------------------------

def triangle_grid(points: np.ndarray, faces: np.ndarray, margin: float):
    """Bin triangles (their boxes grown by `margin`) in a uniform grid.

    Returns (origin (3,), cell size, dims (3,), offsets (cells+1,), triangle ids): the triangles
    overlapping cell c are ids[offsets[c]:offsets[c+1]]; cell (i, j, k) is (i dims[1] + j) dims[2] + k.
    """
    tri = points[faces]
    lo, hi = tri.min(axis=1) - margin, tri.max(axis=1) + margin
    origin = lo.min(axis=0)
    extent = hi.max(axis=0) - origin
    cell = max(float(np.median((hi - lo).max(axis=1))), 1e-12)
    dims = np.floor(extent / cell).astype(np.int64) + 1
    while np.prod(dims) > GRID_MAX_CELLS:
        cell *= 1.26
        dims = np.floor(extent / cell).astype(np.int64) + 1
    i0 = np.floor((lo - origin) / cell).astype(np.int64)
    span = np.floor((hi - origin) / cell).astype(np.int64) - i0 + 1
    count = span.prod(axis=1)
    owner = np.repeat(np.arange(len(faces)), count)
    j = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[owner, 1], span[owner, 2]
    ijk = i0[owner] + np.stack([j // (sy * sz), (j // sz) % sy, j % sz], axis=1)
    cells = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(cells, kind="stable")
    offsets = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    np.cumsum(np.bincount(cells, minlength=int(np.prod(dims))), out=offsets[1:])
    return origin, cell, dims, offsets, owner[order]


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals at the nodes (zero at nodes off the surface)."""
    tri = points[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(points)
    for i in range(3):
        np.add.at(n, faces[:, i], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


@ti.func
def closest_on_triangle(p, a, b, c):
    """Barycentric weights of the point of triangle (a, b, c) closest to p (Ericson, RTCD 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab.dot(ap), ac.dot(ap)
    bp = p - b
    d3, d4 = ab.dot(bp), ac.dot(bp)
    cp = p - c
    d5, d6 = ab.dot(cp), ac.dot(cp)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    w = ti.Vector([0.0, 0.0, 0.0])
    if d1 <= 0.0 and d2 <= 0.0:
        w = ti.Vector([1.0, 0.0, 0.0])
    elif d3 >= 0.0 and d4 <= d3:
        w = ti.Vector([0.0, 1.0, 0.0])
    elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        w = ti.Vector([1.0 - t, t, 0.0])
    elif d6 >= 0.0 and d5 <= d6:
        w = ti.Vector([0.0, 0.0, 1.0])
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        w = ti.Vector([1.0 - t, 0.0, t])
    elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        w = ti.Vector([0.0, 1.0 - t, t])
    else:
        s = 1.0 / (va + vb + vc)
        w = ti.Vector([1.0 - (vb + vc) * s, vb * s, vc * s])
    return w


@ti.kernel
def _soft_kernel(xa: ti.template(), nodes: ti.types.ndarray(), weights: ti.types.ndarray(), xb: ti.template(),
                 faces: ti.types.ndarray(), normals: ti.types.ndarray(), grid: ti.types.ndarray(),
                 dims: ti.types.ndarray(), offsets: ti.types.ndarray(), ids: ti.types.ndarray(),
                 alarm: float, out: ti.types.ndarray(), out_face: ti.types.ndarray()):
    for s in range(nodes.shape[0]):
        p = sample_position(xa, nodes, weights, s)
        origin = ti.Vector([grid[0], grid[1], grid[2]])
        ijk = ti.cast(ti.floor((p - origin) / grid[3]), ti.i32)
        best, best_face = 1e300, -1
        best_w, best_c = ti.Vector([0.0, 0.0, 0.0]), ti.Vector([0.0, 0.0, 0.0])
        if 0 <= ijk[0] < dims[0] and 0 <= ijk[1] < dims[1] and 0 <= ijk[2] < dims[2]:
            cell = (ijk[0] * dims[1] + ijk[1]) * dims[2] + ijk[2]
            for k in range(offsets[cell], offsets[cell + 1]):
                f = ids[k]
                a, b, c = xb[faces[f, 0]], xb[faces[f, 1]], xb[faces[f, 2]]
                w = closest_on_triangle(p, a, b, c)
                q = w[0] * a + w[1] * b + w[2] * c
                d = (p - q).norm()
                if d < best:
                    best, best_face, best_w, best_c = d, f, w, q
        out[s, 0] = 1e300
        out_face[s] = -1
        if best_face >= 0 and best <= alarm:
            f = best_face
            a, b, c = xb[faces[f, 0]], xb[faces[f, 1]], xb[faces[f, 2]]
            vn = ti.Vector([0.0, 0.0, 0.0])
            for i in ti.static(range(3)):
                vn += best_w[i] * ti.Vector([normals[faces[f, i], 0], normals[faces[f, i], 1],
                                             normals[faces[f, i], 2]])
            d = p - best_c
            n = (b - a).cross(c - a).normalized()
            g = 0.0
            if best > 1e-12 * ((b - a).norm() + (c - a).norm()):
                side = 1.0 if d.dot(vn) >= 0.0 else -1.0
                n = side * d / best
                g = side * best
            out[s, 0] = g
            for i in ti.static(range(3)):
                out[s, 1 + i] = n[i]
                out[s, 4 + i] = best_w[i]
                out[s, 7 + i] = best_c[i]
            out_face[s] = f


# --------------------------------------------------------------------------------------------
# the detector
# --------------------------------------------------------------------------------------------

def _nd(a, dtype):
    """A device copy of a constant array (per-step arrays go to kernels as numpy: no allocation)."""
    a = np.ascontiguousarray(a)
    arr = ti.ndarray(dtype=dtype, shape=a.shape)
    arr.from_numpy(a)
    return arr


class Detector:
    """Proximity queries between the soft bodies' surfaces and the rigid obstacles.

    surfaces: per soft body, its boundary triangles (k, 3) as node ids, outward; sampling: which
    contact points each body's surface carries (see `surface_samples`).
    The positions passed to `detect` are per body a Taichi vector field (the solver's `x`, read in
    place) or an (n, 3) numpy array.
    """

    def __init__(self, surfaces, obstacles=(), soft_soft: bool = True, sampling: str = "vertices"):
        be = backend.current()
        self.real, self._np = be.real, (np.float64 if be.real == ti.f64 else np.float32)
        self.faces = [np.asarray(f, dtype=np.int32) for f in surfaces]
        self.samples = [surface_samples(f, sampling) for f in self.faces]
        self.samples = [(n, w.astype(self._np)) for n, w in self.samples]
        self.obstacles = list(obstacles)
        self.soft_soft = soft_soft
        prims = [o.primitives for o in self.obstacles]
        counts = [len(p) for p in prims]
        self.has_primitives = sum(counts) > 0
        if self.has_primitives:
            self._prm = _nd(np.concatenate(prims).astype(self._np), self.real)
            self._offsets = np.r_[0, np.cumsum(counts)].astype(np.int32)
        self._fields = {}

    def _field(self, body, positions):
        """A Taichi field for numpy positions (one per body, reused)."""
        if isinstance(positions, np.ndarray):
            f = self._fields.get(body)
            if f is None or f.shape[0] != len(positions):
                f = self._fields[body] = ti.Vector.field(3, self.real, len(positions))
            f.from_numpy(positions.astype(self._np))
            return f
        return positions

    def detect(self, positions, alarm: float, poses=None, previous_poses=None) -> "Contacts":
        """Contacts of every contact point within `alarm` of an obstacle or another body.

        poses / previous_poses: per obstacle (R, t) now and one step earlier (default: identity);
        the second gives the displacement of the touched material point (for friction)."""
        fields_ = [self._field(b, p) for b, p in enumerate(positions)]
        identity = [(np.eye(3), np.zeros(3))] * len(self.obstacles)
        poses = identity if poses is None else poses
        previous_poses = poses if previous_poses is None else previous_poses
        parts = []
        for b, x in enumerate(fields_):
            if self.obstacles:
                parts.append(self._rigid(b, x, alarm, poses, previous_poses))
            if self.soft_soft:
                for other in range(len(fields_)):
                    if other != b:
                        parts.append(self._soft(b, x, other, fields_[other], alarm))
        return Contacts.concatenate(parts)

    def _rigid(self, b, x, alarm, poses, previous_poses) -> "Contacts":
        nodes, weights = self.samples[b]
        no = len(self.obstacles)
        if self.has_primitives:
            res = np.empty((len(nodes), no, 7), dtype=self._np)
            _rigid_kernel(x, nodes, weights, self._prm, self._offsets,
                          np.array([np.r_[R.reshape(-1), t] for R, t in poses], dtype=self._np), res)
            res = res.astype(np.float64)
        else:
            res = np.full((len(nodes), no, 7), np.inf)
        for o, obstacle in enumerate(self.obstacles):   # triangle meshes: open3d on the host
            if obstacle.meshes:
                R, t = poses[o]
                local = (np.einsum("sj,sji->si", weights, x.to_numpy()[nodes]) - t) @ R
                g, n, c = obstacle.mesh_closest(local)
                better = g < res[:, o, 0]
                res[better, o] = np.column_stack([g, n @ R.T, c @ R.T + t])[better]
        s, o = np.nonzero(res[:, :, 0] <= alarm)
        k = len(s)
        point = res[s, o, 4:7]
        # The material point of the obstacle now at `point` was, one step earlier, at
        # R0 R1ᵀ (point - t1) + t0.
        motion = np.zeros((k, 3))
        for j in np.unique(o):
            (R1, t1), (R0, t0) = poses[j], previous_poses[j]
            sel = o == j
            motion[sel] = point[sel] - ((point[sel] - t1) @ R1 @ R0.T + t0)
        return Contacts(body=np.full(k, b, np.int32), sample=s.astype(np.int32), nodes=nodes[s],
                        own_weights=weights[s].astype(np.float64), other=o.astype(np.int32),
                        soft=np.zeros(k, bool), triangle=np.full((k, 3), -1, np.int32), weights=np.zeros((k, 3)),
                        normal=res[s, o, 1:4], gap=res[s, o, 0], closest=point, other_motion=motion)

    def _soft(self, b, xa, other, xb, alarm) -> "Contacts":
        pb = xb.to_numpy().astype(np.float64)
        faces = self.faces[other]
        origin, cell, dims, offsets, ids = triangle_grid(pb, faces, alarm)
        nodes, weights = self.samples[b]
        if len(nodes) == 0:
            return Contacts.empty()
        res, face = np.empty((len(nodes), 10), dtype=self._np), np.empty(len(nodes), dtype=np.int32)
        _soft_kernel(xa, nodes, weights, xb, faces, vertex_normals(pb, faces).astype(self._np),
                     np.r_[origin, cell].astype(self._np), dims.astype(np.int32), offsets.astype(np.int32),
                     ids.astype(np.int32), alarm, res, face)
        res = res.astype(np.float64)
        s = np.flatnonzero(face >= 0)
        k = len(s)
        return Contacts(body=np.full(k, b, np.int32), sample=s.astype(np.int32), nodes=nodes[s],
                        own_weights=weights[s].astype(np.float64), other=np.full(k, other, np.int32),
                        soft=np.ones(k, bool), triangle=faces[face[s]].astype(np.int32), weights=res[s, 4:7],
                        normal=res[s, 1:4], gap=res[s, 0], closest=res[s, 7:10], other_motion=np.zeros((k, 3)))
