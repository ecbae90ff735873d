"""Proximity detection: the contact points of each soft body's surface that lie within the
contact (alarm) distance of a rigid obstacle or of another soft body's surface.

What a contact point and a contact are: tissue.contact.contacts.

  soft–rigid  one thread per sample, for each obstacle the nearest of its primitives in the
              obstacle's frame, skipping the obstacle whose bounding ball, and the primitives
              whose bounding box, or their group's (a run of touching primitives: a rib), is
              beyond the alarm distance; an obstacle of many primitives also keeps a grid of them
              in its frame, whose cell lists those a sample near it may reach; triangle-mesh
              obstacles are queried on the host with open3d (closest point, and inside/outside
              by ray parity).
  soft–soft   broad phase: the other body's surface triangles, their boxes grown by the alarm
              distance and a skin, binned in a uniform grid built on the device (box, counting
              sort) and kept, Verlet-style, until a surface node has moved by more than the skin
              (`_detect_soft` says why the hits are the same); narrow phase: one thread per
              sample, exact point–triangle distance to the triangles of its cell whose box is
              within the alarm distance (Ericson's Voronoi-region test), ties to the lowest
              triangle id. Inside/outside is the sign of (p - c) against the interpolated
              area-weighted vertex normal at c, which stays right at edges and corners where a
              face normal can point either way. Both directions are detected (samples of A
              against triangles of B and of B against A).

For one body this is a kernel launch against the obstacles (`_detect_rigid`) and one against each
other soft body (`_detect_soft`), writing into a buffer kept between calls (`HitBuffer`,
tissue.contact.hits, which reads the hits as Contacts); the first also copies
the body's positions and start-of-step positions for the constraints. Two kernels, not one with
template switches: each compiles once for every scene, so a scene with rigid contacts only and one
with soft–soft contacts too fill Taichi's offline cache for each other.
Detection reads the positions after the free motion. Against rigid obstacles a contact point is
also a contact when it was within the alarm distance at the step's start (given the velocities:
start = free − h v), by the gap at the free position less the free motion along the normal,
g − n·(p − p₀): the free motion ignores contacts, so a body resting on a floor falls g h² in it
(15.7 mm at h = 0.04 s), and a plate resting on its top would be that far away at the free
positions, out of any alarm distance, and pass through it unseen. The row is still linearised at
the free position (its gap there, positive), so it pushes only where the correction would bring
the point back past the obstacle. Soft–soft contacts are found at the free positions only.
Results come back as numpy arrays, sorted by (body, sample, kind, other), so runs are
deterministic.
"""

import operator
from dataclasses import dataclass

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..launch import kept_pack, replayed
from .contacts import Contacts, surface_samples
from .constraints import offsets
from .geometry import (cell_range, closest_on_primitive, closest_on_triangle, primitive_bounds, primitive_grid,
                       sample_point, vector_at, within_ball, within_box, within_corners)
from .hits import HitBuffer
from .storage import Storage

GRID_MAX_CELLS = 1 << 18   # the soft–soft grid grows its cells rather than exceed this
GRID_SKIN = 0.5     # the soft–soft grid is kept while the surface moves less than this times the alarm distance
# Room for rounding in the soft–soft pruning: ROOM of the alarm distance, or ROUNDING_ULPS units of
# rounding of the coordinates' size where more (float32, or bodies far from the origin): the
# distances it compares are rounded at the coordinates' scale, not the alarm distance's.
ROOM = 1e-5
ROUNDING_ULPS = 16
SERIAL_BELOW_POINTS = 30_000      # contact points: below, the CPU runs the detection loops on one thread


def _serial(samples) -> bool:
    """Small problems run each loop on one thread on the CPU: dispatching a few hundred iterations
    to the thread pool costs more than it saves."""
    return backend.current().arch == "cpu" and sum(len(nodes) for nodes, _ in samples) < SERIAL_BELOW_POINTS


# The arrays of a detection launch, in one flat argpack holding only what it reads (the launcher
# costs per ndarray, replayed or not): body A's positions, samples and (for the start of the step)
# velocities (OWN), then the obstacles' primitives and their bounds (RIGID), or body B's
# positions, surface, faces around each node and triangle grid (SOFT).
OWN_MEMBERS = ("xa", "nodes", "weights", "va")
RIGID_MEMBERS = (*OWN_MEMBERS, "prm", "prm_index", "prm_bounds", "bounds")
SOFT_MEMBERS = (*OWN_MEMBERS, "xb", "faces", "surface", "vf_offsets", "vf", "reference", "start", "cursor", "ids",
                "grid_i", "grid_f")
DETECT_RIGID = ti.types.argpack(**{name: ti.types.ndarray() for name in RIGID_MEMBERS})
DETECT = ti.types.argpack(**{name: ti.types.ndarray() for name in SOFT_MEMBERS})


@ti.func
def _copy_state(det: ti.template(), state: ti.template(), h, copy_state, serial: ti.template()):
    """With copy_state (0 or 1): state[k] = (x_k, x_k - h v_k), body A's free and start positions
    (the constraints need them); a loop of 0 iterations without (a runtime flag: every scene's
    launches share one instance)."""
    ti.loop_config(serialize=serial)
    for k in range(det.xa.shape[0] * copy_state):
        p, u = det.xa[k], det.va[k]
        for c in ti.static(range(3)):
            state[k, c] = p[c]
            state[k, 3 + c] = p[c] - h * u[c]


@ti.kernel
def _detect_rigid(det: DETECT_RIGID, poses: ti.types.ndarray(), gap: ti.types.ndarray(), out: ti.types.ndarray(),
                  state: ti.types.ndarray(), alarm: float, h: float, copy_state: ti.i32, serial: ti.template()):
    """Body A's contact candidates on the obstacles, in one launch: every (sample, obstacle)
    pair, the nearest of the obstacle's primitives. gap[s, o]: its gap, 1e300 for none; a hit's
    out[s, o] = [normal (3), closest point (3), 0 (3), -1]. poses[o]: obstacle o's rotation R
    (row-major), translation t and bounding ball in the world frame (centre, radius; < 0:
    unbounded). copy_state: see _copy_state."""
    _copy_state(det, state, h, copy_state, serial)
    ns = det.nodes.shape[0]
    ti.loop_config(serialize=serial)
    for s in range(ns):
        # A cheap test first, in the world frame: the sample beyond the obstacle's ball grown by
        # the alarm distance and the sample's free motion (with room for rounding: an isometry's
        # distances are the same) cannot pass the test in the obstacle's frame below; the pairs
        # that may are tested there as they are, so the hits do not change.
        free = sample_point(det.xa, det.nodes, det.weights, s)
        grow = alarm + h * sample_point(det.va, det.nodes, det.weights, s).norm()
        for o in range(det.bounds.shape[0]):     # (not ti.ndrange: it divides for its indices)
            d = free - ti.Vector([poses[o, 12], poses[o, 13], poses[o, 14]])
            bound = (poses[o, 15] + grow) * (1.0 + 1e-9)
            if poses[o, 15] >= 0.0 and d.dot(d) > bound * bound:
                gap[s, o] = 1e300
                continue
            R = ti.Matrix([[poses[o, 0], poses[o, 1], poses[o, 2]], [poses[o, 3], poses[o, 4], poses[o, 5]],
                           [poses[o, 6], poses[o, 7], poses[o, 8]]])
            t = ti.Vector([poses[o, 9], poses[o, 10], poses[o, 11]])
            p = R.transpose() @ (sample_point(det.xa, det.nodes, det.weights, s) - t)
            best = ti.Vector([1e300, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
            # Bounds farther than `reach` skip what they hold, which cannot be within it: the
            # obstacle's ball (radius < 0: unbounded, a plane) all its primitives, a group's box
            # (see primitive_bounds) the group's, a primitive's box the primitive; within its
            # grid's margin (grow is reach but for rounding, which the grid's room for rounding
            # covers), p's cell (see primitive_grid) lists all primitives that may be. Those
            # tested are tested in order, so the nearest (ties: the first) is the one all of
            # them would give. They are the primitives in turn from k to
            # stop: the obstacle's, a group skipped at its first where its box is beyond reach;
            # or, listed, those of p's cell (one loop: the closest-point code is compiled once).
            k, stop, listed = det.prm_index[o], det.prm_index[o + 1], grow <= det.bounds[o, 12]
            if listed:
                ijk = ti.cast(ti.floor((p - vector_at(det.bounds, o, 4)) / det.bounds[o, 7]), ti.i32)
                dims = ti.cast(vector_at(det.bounds, o, 8), ti.i32)
                k, stop = 0, 0
                if 0 <= ijk[0] < dims[0] and 0 <= ijk[1] < dims[1] and 0 <= ijk[2] < dims[2]:
                    cid = ti.cast(det.bounds[o, 11], ti.i32) + (ijk[0] * dims[1] + ijk[1]) * dims[2] + ijk[2]
                    k, stop = det.prm_index[cid], det.prm_index[cid + 1]
            moved = ti.Vector([0.0, 0.0, 0.0])        # (nothing to test: no hit, whatever the motion)
            if k < stop:
                moved = R.transpose() @ (h * sample_point(det.va, det.nodes, det.weights, s))     # the free motion (0 without v)
                reach = alarm + moved.norm()
                if listed or within_ball(det.bounds, o, p, reach):
                    group_end = k
                    while k < stop:
                        if not listed and k == group_end:
                            group_end = ti.cast(det.prm_bounds[k, 12], ti.i32)
                            if not within_box(det.prm_bounds, k, 6, p, reach):
                                k = group_end
                                continue
                        j = k
                        if listed:
                            j = det.prm_index[k]
                        if within_box(det.prm_bounds, j, 0, p, reach):
                            r = closest_on_primitive(det.prm, j, p)
                            if r[0] < best[0]:
                                best = r
                        k += 1
            # Within `alarm` at the free position, or at the step's start (the gap less the free
            # motion along the normal): see the module docstring.
            start_gap = best[0] - moved.dot(ti.Vector([best[1], best[2], best[3]]))
            gap[s, o] = best[0] if ti.min(best[0], start_gap) <= alarm else 1e300
            if gap[s, o] < 1e300:                   # the host reads the rest of hits only
                n = R @ ti.Vector([best[1], best[2], best[3]])
                c = R @ ti.Vector([best[4], best[5], best[6]]) + t
                for i in ti.static(range(3)):
                    out[s, o, i] = n[i]
                    out[s, o, 3 + i] = c[i]
                    out[s, o, 6 + i] = 0.0
                out[s, o, 9] = -1.0


@ti.func
def _vertex_normal(det: ti.template(), node):
    """Body B's area-weighted normal at a surface node: its faces' cross products summed in
    ascending face id, normalised."""
    nv = ti.Vector([0.0, 0.0, 0.0])
    for m in range(det.vf_offsets[node], det.vf_offsets[node + 1]):
        f = det.faces[det.vf[m]]
        nv += (det.xb[f[1]] - det.xb[f[0]]).cross(det.xb[f[2]] - det.xb[f[0]])
    return nv / ti.max(nv.norm(), 1e-300)


@ti.func
def _with_room(det: ti.template(), alarm):
    """The alarm distance and room for rounding (see ROOM) at the coordinates' size of the grid kept."""
    return ti.max(alarm * (1.0 + ROOM), alarm + det.grid_f[5])


@ti.kernel
def _detect_soft(det: DETECT, gap: ti.types.ndarray(), out: ti.types.ndarray(), state: ti.types.ndarray(),
                 cell0: float, alarm: float, margin: float, slot: ti.i32, h: float, copy_state: ti.i32,
                 serial: ti.template()):
    """Body A's contact candidates on body B's surface, in one launch: B's triangle grid (box,
    counting sort) unless the one kept still holds, then per sample the nearest triangle of its
    cell within `alarm`. gap[s, slot]: its gap, 1e300 for none; a hit's out[s, slot] = [normal
    (3), closest point (3), weights on B's triangle (3), triangle id]. copy_state: see _copy_state.

    The grid bins each triangle in the cells its box grown by `margin` (> alarm) meets, and keeps
    B's surface positions it was built from (`reference`): while no surface node has moved by
    more than margin − alarm along any axis since (less room for rounding: ROOM), each triangle
    lies within its binned box shrunk by alarm, so a sample within alarm of it still lies in a
    cell it is binned in, and the grid is kept (grid_i[5]: built whole; grid_i[6]: built at this
    launch). The sample's nearest triangle is the same in any cell that holds it (ties: the lowest
    id), so the hits do not depend on when the grid was built."""
    _copy_state(det, state, h, copy_state, serial)
    ns = det.nodes.shape[0]
    nf = det.faces.shape[0]
    ti.loop_config(serialize=serial)
    for _ in range(1):                          # serial: whether the grid holds; if not, its box, cell size and dims
        holds = det.grid_i[5] == 1
        slack = det.grid_f[4] - _with_room(det, alarm)    # the margin it was built with, beyond the alarm distance
        m = 0
        while holds and m < det.surface.shape[0]:
            holds = (ti.abs(det.xb[det.surface[m]] - det.reference[m])).max() <= slack
            m += 1
        det.grid_i[6] = 0 if holds else 1
        if not holds:
            lo = ti.Vector([1e300, 1e300, 1e300])
            hi = -lo
            for k in range(det.surface.shape[0]):
                p = det.xb[det.surface[k]]
                det.reference[k] = p
                lo, hi = ti.min(lo, p), ti.max(hi, p)
            det.grid_f[5] = det.grid_f[6] * ti.max(ti.abs(lo), ti.abs(hi)).max()    # see ROOM
            lo -= margin
            hi += margin
            cell = cell0
            extent = (hi - lo) / cell
            while (extent[0] + 1.0) * (extent[1] + 1.0) * (extent[2] + 1.0) > GRID_MAX_CELLS:
                cell *= 1.26
                extent = (hi - lo) / cell
            dims = ti.cast(ti.floor(extent), ti.i32) + 1
            for i in ti.static(range(3)):
                det.grid_f[i] = lo[i]
                det.grid_i[i] = dims[i]
            det.grid_f[3] = cell
            det.grid_f[4] = margin
            det.grid_i[3] = dims[0] * dims[1] * dims[2]
    origin = ti.Vector([det.grid_f[0], det.grid_f[1], det.grid_f[2]])
    cell = det.grid_f[3]
    dims = ti.Vector([det.grid_i[0], det.grid_i[1], det.grid_i[2]])
    reach = _with_room(det, alarm)
    ti.loop_config(serialize=serial)
    for c in range((det.grid_i[3] + 1) * det.grid_i[6]):
        det.start[c] = 0
    ti.loop_config(serialize=serial)
    for f in range(nf * det.grid_i[6]):         # count the triangles of each cell
        a, b, c = det.xb[det.faces[f][0]], det.xb[det.faces[f][1]], det.xb[det.faces[f][2]]
        i0, i1 = cell_range(ti.min(a, b, c) - margin, ti.max(a, b, c) + margin, origin, cell, dims)
        for i in range(i0[0], i1[0] + 1):       # (nested: an inner ti.ndrange divides for its indices)
            for j in range(i0[1], i1[1] + 1):
                for k in range(i0[2], i1[2] + 1):
                    ti.atomic_add(det.start[(i * dims[1] + j) * dims[2] + k + 1], 1)
    ti.loop_config(serialize=serial)
    for _ in range(1):                          # serial prefix sum: start[c] .. start[c + 1]
        if det.grid_i[6]:
            for c in range(det.grid_i[3]):
                det.start[c + 1] += det.start[c]
                det.cursor[c] = det.start[c]
            det.grid_i[4] = det.start[det.grid_i[3]]
            det.grid_i[5] = 1 if det.grid_i[4] <= det.ids.shape[0] else 0
        gap[ns, slot] = ti.cast(det.grid_i[4], float)   # the host grows `ids` if it overflowed
    ti.loop_config(serialize=serial)
    for f in range(nf * det.grid_i[6]):         # fill (order within a cell: any; see below)
        if det.grid_i[5]:
            a, b, c = det.xb[det.faces[f][0]], det.xb[det.faces[f][1]], det.xb[det.faces[f][2]]
            i0, i1 = cell_range(ti.min(a, b, c) - margin, ti.max(a, b, c) + margin, origin, cell, dims)
            for i in range(i0[0], i1[0] + 1):
                for j in range(i0[1], i1[1] + 1):
                    for k in range(i0[2], i1[2] + 1):
                        det.ids[ti.atomic_add(det.cursor[(i * dims[1] + j) * dims[2] + k], 1)] = f
    ti.loop_config(serialize=serial)
    for s in range(ns):                         # narrow phase
        gap[s, slot] = 1e300
        p = sample_point(det.xa, det.nodes, det.weights, s)
        ijk = ti.cast(ti.floor((p - origin) / cell), ti.i32)
        best, best_face = 1e300, -1
        best_w, best_c = ti.Vector([0.0, 0.0, 0.0]), ti.Vector([0.0, 0.0, 0.0])
        if det.grid_i[5] and 0 <= ijk[0] < dims[0] and 0 <= ijk[1] < dims[1] and 0 <= ijk[2] < dims[2]:
            cid = (ijk[0] * dims[1] + ijk[1]) * dims[2] + ijk[2]
            for m in range(det.start[cid], det.start[cid + 1]):
                f = det.ids[m]
                a, b, c = det.xb[det.faces[f][0]], det.xb[det.faces[f][1]], det.xb[det.faces[f][2]]
                # A triangle whose box is beyond the alarm distance (with room for rounding) is
                # farther: it cannot be the nearest of a hit, and is not measured.
                if within_corners(ti.min(a, b, c), ti.max(a, b, c), p, reach):
                    w = closest_on_triangle(p, a, b, c)
                    q = w[0] * a + w[1] * b + w[2] * c
                    d = (p - q).norm()
                    # Ties (a point nearest to a shared edge or vertex) go to the lowest triangle
                    # id, so the result does not depend on the order the cell was filled in.
                    if d < best or (d == best and f < best_face):
                        best, best_face, best_w, best_c = d, f, w, q
        if best_face >= 0 and best <= alarm:
            f = det.faces[best_face]
            a, b, c = det.xb[f[0]], det.xb[f[1]], det.xb[f[2]]
            vn = ti.Vector([0.0, 0.0, 0.0])
            for i in range(3):                  # (not unrolled: the normal's code is compiled once)
                corner = f[0] if i == 0 else (f[1] if i == 1 else f[2])
                vn += (best_w[0] if i == 0 else (best_w[1] if i == 1 else best_w[2])) * _vertex_normal(det, corner)
            d = p - best_c
            n = (b - a).cross(c - a).normalized()
            g = 0.0
            if best > 1e-12 * ((b - a).norm() + (c - a).norm()):
                side = 1.0 if d.dot(vn) >= 0.0 else -1.0
                n = side * d / best
                g = side * best
            gap[s, slot] = g
            for i in ti.static(range(3)):
                out[s, slot, i] = n[i]
                out[s, slot, 3 + i] = best_c[i]
                out[s, slot, 6 + i] = best_w[i]
            out[s, slot, 9] = ti.cast(best_face, float)


@ti.kernel
def read_state(x: ti.types.ndarray(), v: ti.types.ndarray(), h: float, out: ti.types.ndarray()):
    """out[k] = (x_k, x_k - h v_k): the free positions and those at the start of the step."""
    for k in range(x.shape[0]):
        p, u = x[k], v[k]
        for c in ti.static(range(3)):
            out[k, c] = p[c]
            out[k, 3 + c] = p[c] - h * u[c]


# --------------------------------------------------------------------------------------------
# the detector
# --------------------------------------------------------------------------------------------

def _array(values: np.ndarray, dtype, n: int = 0) -> ti.Ndarray:
    """An ndarray (of n-vectors when n > 0) holding `values` (at least one element).

    The detection data are ndarrays, not fields: the detection kernels take them as ndarray
    parameters, so each compiles once for every body and scene (a field per body would compile it
    again for each)."""
    values = np.ascontiguousarray(values)
    a = ti.ndarray(ti.types.vector(n, dtype) if n else dtype, max(1, len(values)))
    if len(values):
        a.from_numpy(values)
    return a


class _Surface:
    """One body's constant detection data on the device, and its rows of the hit buffer."""

    def __init__(self, faces, samples, n_nodes, gap, out, real, npr):
        nodes, weights = samples
        self.faces_np = faces
        self.n_samples = len(nodes)
        surface = np.unique(faces).astype(np.int32)
        # Faces around each node (CSR by node id, ascending face id), for the vertex normals.
        self.n_nodes = n_nodes
        corners = faces.reshape(-1)
        face_offsets = np.zeros(n_nodes + 1, np.int32)
        np.cumsum(np.bincount(corners, minlength=n_nodes), out=face_offsets[1:])
        self.nodes, self.weights = _array(nodes, ti.i32, 3), _array(weights.astype(npr), real, 3)
        self.faces = _array(faces, ti.i32, 3)
        self.surface = _array(surface, ti.i32)
        self.vf_offsets = _array(face_offsets, ti.i32)
        self.vf = _array((np.argsort(corners, kind="stable") // 3).astype(np.int32), ti.i32)
        # The grid of this body's triangles (built on the device when the one kept no longer
        # holds: _detect_soft), and the surface positions it was built from.
        self.start = ti.ndarray(ti.i32, GRID_MAX_CELLS + 1)
        self.cursor = ti.ndarray(ti.i32, GRID_MAX_CELLS)
        # grid_f: origin (3), cell size, margin, room for rounding at the coordinates' size, and
        # that room per unit of size (see ROOM).
        self.grid_i = _array(np.zeros(8, np.int32), ti.i32)
        self.grid_f = _array(np.r_[np.zeros(6), ROUNDING_ULPS * np.finfo(npr).eps].astype(npr), real)
        self.reference = ti.ndarray(ti.types.vector(3, real), max(len(surface), 1))
        self.cell = None                          # base cell size: set at the first detection
        self.cell0 = self.margin = None           # the launch's cell0 and margin (_run_soft)
        self.gap, self.out = gap, out             # its rows of the Detector's HitBuffer


# The detection launch repeats its arguments step after step (the bodies' arrays, the buffers kept
# here): replayed, it skips Taichi's setting of its ~30 arguments.
_detect_rigid_replayed, _detect_soft_replayed = replayed(_detect_rigid), replayed(_detect_soft)


@dataclass
class _BodyDetection:
    """Body A's detection in a step: what its launches (and its triangle-mesh obstacles' queries)
    read besides the Detector's arrays, and where they write."""

    index: int                  # A, among the bodies
    x: ti.Ndarray               # its positions (3-vectors)
    v: ti.Ndarray | None        # its velocities: with them, its first launch copies x and x - dt v
    state: np.ndarray           # ... into this (n, 6) array (Detector.state[A]); without, a stand-in
    surface: _Surface           # its arrays on the device, and its rows of the hit buffer
    others: list                # the bodies it is tested against, in its slots' order after the obstacles
    alarm: float
    dt: float


class Detector:
    """Proximity queries between the soft bodies' surfaces and the rigid obstacles.

    surfaces: per soft body, its boundary triangles (k, 3) as node ids, outward; sampling: which
    contact points each body's surface carries (see `surface_samples`).
    The positions passed to `detect` are per body a Taichi ndarray of 3-vectors (the solver's `x`,
    read in place) or an (n, 3) numpy array. Each body's detection is a kernel launch against the
    obstacles and one against each other soft body, writing into a buffer kept between calls.
    """

    def __init__(self, surfaces, obstacles=(), soft_soft: bool = True, sampling: str = "vertices"):
        be = backend.current()
        self.real, self._np = be.real, (np.float64 if be.real == ti.f64 else np.float32)
        self.faces = [np.asarray(f, dtype=np.int32).reshape(-1, 3) for f in surfaces]
        self.samples = [surface_samples(f, sampling) for f in self.faces]
        self.samples = [(n, w.astype(self._np)) for n, w in self.samples]
        self.obstacles = list(obstacles)
        self.soft_soft, self.sampling = soft_soft, sampling
        prims = [o.primitives for o in self.obstacles]
        counts = [len(p) for p in prims]
        self.has_primitives = sum(counts) > 0
        firsts = offsets(counts)             # each obstacle's first primitive, and the end
        self._prm = ti.ndarray(self.real, (max(1, sum(counts)), 16))
        self._prm_bounds = ti.ndarray(self.real, (max(1, sum(counts)), 13))
        if self.has_primitives:
            self._prm.from_numpy(np.concatenate(prims).astype(self._np))
            self._prm_bounds.from_numpy(np.concatenate(
                [primitive_bounds(o.bounding_boxes(), start) for o, start in zip(self.obstacles, firsts)]
            ).astype(self._np))
        self._balls = np.array([o.bounding_ball() for o in self.obstacles]).reshape(-1, 4)
        # Per obstacle its ball and its grid (see primitive_grid; margin -1: none); the obstacles'
        # first primitives, then their grids' cell starts and primitive ids.
        bounds = np.zeros((max(1, len(self.obstacles)), 13))
        bounds[:len(self.obstacles), :4], bounds[:, 12] = self._balls, -1.0
        index = [firsts]
        for o, obstacle in enumerate(self.obstacles):
            grid = primitive_grid(obstacle.bounding_boxes(), firsts[o], sum(map(len, index)))
            if grid is not None:
                bounds[o, 4:], part = grid
                index.append(part)
        self._bounds = ti.ndarray(self.real, bounds.shape)
        self._bounds.from_numpy(bounds.astype(self._np))
        self._prm_index = _array(np.concatenate(index).astype(np.int32), ti.i32)
        self._obstacle_arrays = (self._prm, self._prm_index, self._prm_bounds, self._bounds)   # RIGID_MEMBERS after OWN
        self._moving_ids = [j for j, o in enumerate(self.obstacles) if o.motion is not None]
        self._poses = np.zeros((max(1, len(self.obstacles)), 16), self._np)    # see _detect_rigid
        self._packed = (None,) * len(self.obstacles)     # the poses _poses holds
        self._fields = {}
        self._packs = {}                          # per body pair, the launch's argpack (see _pack)
        self._bodies = None
        # Per body its (n, 6) rows of `states` (every body's, body b's from state_offset[b]: one
        # array for tissue.contact.row_writer's launch)
        self.state, self.states, self.state_offset, self._no_state = None, None, None, np.zeros((1, 6))
        self.storage = Storage()                  # per body, the ids of its triangle grid's cells
        self.serial = _serial(self.samples)

    def set_surface(self, body: int, faces) -> None:
        """Replace a body's surface triangles (after a topology edit); its samples follow."""
        self.faces[body] = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
        nodes, weights = surface_samples(self.faces[body], self.sampling)
        self.samples[body] = (nodes, weights.astype(self._np))
        self._bodies = None
        self.serial = _serial(self.samples)

    def _field(self, body, positions):
        """A Taichi ndarray for numpy positions (one per body, reused); a solver's `x` as it is."""
        if isinstance(positions, np.ndarray):
            f = self._fields.get(body)
            if f is None or f.shape[0] != len(positions):
                f = self._fields[body] = ti.ndarray(ti.types.vector(3, self.real), len(positions))
            f.from_numpy(positions.astype(self._np))
            return f
        return positions

    def _setup(self, fields_):
        sizes = [f.shape[0] for f in fields_]
        if self._bodies is None or [b.n_nodes for b in self._bodies] != sizes:
            for b, (faces, n) in enumerate(zip(self.faces, sizes)):
                if faces.size and faces.max() >= n:       # (the kernels would read beyond the positions)
                    raise TissueError(f"soft body {b}: its surface names node {faces.max()}, "
                                      f"but it has {n} positions")
            self._hits = HitBuffer(self.samples, self.faces, len(self.obstacles), self.soft_soft, self._np)
            self._bodies = [_Surface(f, s, n, gap, out, self.real, self._np)
                            for f, s, n, (gap, out) in zip(self.faces, self.samples, sizes, self._hits.outs)]

    def detect(self, positions, alarm: float, poses=None, previous_poses=None, velocities=None,
               dt: float = 0.0) -> Contacts:
        """Contacts of every contact point within `alarm` of an obstacle or another body.

        poses / previous_poses: per obstacle (R, t) now and one step earlier (default: identity);
        the second gives the displacement of the touched material point (for friction).
        velocities (per body its solver's velocity ndarray, with `dt`): also read each body's positions x and
        x - dt v into `self.state[b]` ((n, 6) numpy) in the same launches."""
        fields_ = [self._field(b, p) for b, p in enumerate(positions)]
        self._setup(fields_)
        no = len(self.obstacles)
        poses = [(np.eye(3), np.zeros(3))] * no if poses is None else poses
        previous_poses = poses if previous_poses is None else previous_poses
        packed = self._poses                  # filled in place: the launches replay (tissue.launch)
        if not all(map(operator.is_, poses, self._packed)):     # (a static obstacle hands one read-only pose)
            for o, (R, t) in enumerate(poses):
                ball = self._balls[o]
                packed[o, :9], packed[o, 9:12] = R.reshape(-1), t
                packed[o, 12:15], packed[o, 15] = R @ ball[:3] + t, ball[3]
            self._packed = tuple(poses)
        sizes = [f.shape[0] for f in fields_]
        if velocities is not None and (self.state is None or [len(s) for s in self.state] != sizes):
            self.state_offset = offsets(sizes).astype(np.int32)
            self.states = np.empty((self.state_offset[-1], 6), np.float64)
            self.state = [self.states[a:b] for a, b in zip(self.state_offset[:-1], self.state_offset[1:])]
        for a, x in enumerate(fields_):
            v = None if velocities is None else velocities[a]
            body = _BodyDetection(a, x, v, self._no_state if v is None else self.state[a], self._bodies[a],
                                  [b for b in range(len(fields_)) if b != a] if self.soft_soft else [], alarm, dt)
            self._run(body, fields_, packed)
            for o, obstacle in enumerate(self.obstacles):   # triangle meshes: open3d on the host
                if obstacle.meshes:
                    self._mesh(body, o, obstacle, poses[o])
        return self._hits.contacts(poses, previous_poses, self._moving_ids)

    def _run(self, body: _BodyDetection, fields_, poses) -> None:
        """Body A's launches: one against the obstacles' primitives and one against each other
        body (`fields_`: every body's positions); the first also copies its state (with v)."""
        surface, no = body.surface, len(self.obstacles)
        if not self.has_primitives:
            surface.gap[:, :no] = 1e300
        if not (self.has_primitives or body.others) or surface.n_samples == 0:
            if body.v is not None:
                read_state(body.x, body.v, body.dt, body.state)
            return
        launches = [(body.others[0] if body.others else body.index, self.has_primitives, bool(body.others))]
        launches += [(b, False, True) for b in body.others[1:]]
        own = (body.x, surface.nodes, surface.weights, body.x if body.v is None else body.v)   # OWN_MEMBERS
        for k, (b, rigid, soft) in enumerate(launches):
            copy_state = int(body.v is not None and k == 0)
            if rigid:
                pack = self._pack((body.index, None), DETECT_RIGID, (*own, *self._obstacle_arrays))
                _detect_rigid_replayed(pack, poses, surface.gap, surface.out, body.state, body.alarm, body.dt,
                                       copy_state, self.serial)
            if soft:
                self._run_soft(body, own, b, fields_[b], 0 if rigid else copy_state)

    def _run_soft(self, body: _BodyDetection, own, b, xb, copy_state) -> None:
        """Body A's launch against body b's surface at positions xb (`own`: body A's arrays of the
        launch, OWN_MEMBERS)."""
        other = self._bodies[b]
        if other.cell is None:                        # the median triangle extent, at the first call
            tri = xb.to_numpy().astype(np.float64)[other.faces_np]
            other.cell = max(float(np.median((tri.max(axis=1) - tri.min(axis=1)).max(axis=1))), 1e-12)
        ids = self.storage.get(b, max(1024, 27 * len(other.faces_np)), ti.i32)
        slot = len(self.obstacles) + body.others.index(b)
        gap = body.surface.gap
        margin = (1.0 + GRID_SKIN) * body.alarm
        if margin != other.margin:      # else the same float objects as before: the launch replays by identity
            other.margin, other.cell0 = margin, other.cell + 2 * margin
        while True:
            pack = self._pack((body.index, b), DETECT, (*own, xb, other.faces, other.surface, other.vf_offsets,
                                                        other.vf, other.reference, other.start, other.cursor, ids,
                                                        other.grid_i, other.grid_f))     # SOFT_MEMBERS
            _detect_soft_replayed(pack, gap, body.surface.out, body.state, other.cell0, body.alarm, other.margin,
                                  slot, body.dt, copy_state, self.serial)
            needed = int(gap[-1, slot])
            if needed <= ids.shape[0]:
                return
            ids = self.storage.get(b, needed, ti.i32)          # grow and redo (rare)

    def _pack(self, pair, kind, arrays: tuple):
        """The launch's argpack (`kind`, its arrays in its members' order) for the body pair `pair`
        (b None: the obstacles), rebuilt only when one of its arrays is another object (a grown
        grid, new bodies): the same pack step after step replays."""
        kept = self._packs[pair] = kept_pack(self._packs.get(pair), kind, arrays)
        return kept[0]

    def _mesh(self, body: _BodyDetection, o, obstacle, pose) -> None:
        """Body A's hits on triangle-mesh obstacle o (open3d), by the kernel's rule for primitives:
        within the alarm distance at the free position or, given the velocities, at the step's
        start (body.state holds it)."""
        nodes, weights = self.samples[body.index]
        R, t = pose
        points = np.einsum("sj,sji->si", weights, body.x.to_numpy()[nodes])
        local = (points - t) @ R
        g, n, c = obstacle.mesh_closest(local)
        start_gap = g
        if body.v is not None:
            start = body.state[:, 3:]
            start_gap = g - np.einsum("si,si->s", n @ R.T, points - np.einsum("sj,sji->si", weights, start[nodes]))
        gaps, res = body.surface.gap[:-1, o], body.surface.out[:-1, o]
        better = (np.minimum(g, start_gap) <= body.alarm) & (g < gaps)
        gaps[better] = g[better]
        res[better, :6] = np.column_stack([n @ R.T, c @ R.T + t])[better]
        res[better, 6:9], res[better, 9] = 0.0, -1.0
