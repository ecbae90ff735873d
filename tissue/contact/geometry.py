"""The geometry the detection kernels ask (tissue.contact.detection): the contact point of a
body's sample, closest points (on a primitive of an obstacle, on a triangle), the bounds that skip
what lies beyond the alarm distance (an obstacle's ball, its primitives' boxes and their groups',
its grid of primitives), and the cells of the soft–soft triangle grid a box meets.

The primitives are the packed rows of tissue.contact.obstacles, in the obstacle's frame; the
bounds' rows are built on the host (`primitive_bounds`) and read in the kernels (`within_box`).
"""

import numpy as np
import taichi as ti

from .obstacles import BOX, CAPSULE, PLANE, SPHERE


@ti.func
def vector_at(rows: ti.template(), k, i):
    """The 3-vector in row k's columns i..i+2 of a packed 2-d array."""
    return ti.Vector([rows[k, i], rows[k, i + 1], rows[k, i + 2]])


@ti.func
def closest_on_ball(p, centre, radius):
    """Signed distance, normal and closest point of a ball (also the capsule around its axis)."""
    d = p - centre
    length = d.norm()
    n = ti.Vector([0.0, 0.0, 1.0])
    if length > 1e-300:
        n = d / length
    c = centre + radius * n
    return ti.Vector([length - radius, n[0], n[1], n[2], c[0], c[1], c[2]])


@ti.func
def closest_on_primitive(prm: ti.template(), k, p):
    """[gap, normal (3), closest point (3)] of point p to primitive k (all in its frame)."""
    kind = ti.cast(prm[k, 0], ti.i32)
    out = ti.Vector([1e300, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    if kind == PLANE:
        o, n = vector_at(prm, k, 1), vector_at(prm, k, 4)
        g = (p - o).dot(n)
        c = p - g * n
        out = ti.Vector([g, n[0], n[1], n[2], c[0], c[1], c[2]])
    elif kind == SPHERE:
        out = closest_on_ball(p, vector_at(prm, k, 1), prm[k, 4])
    elif kind == CAPSULE:
        a, b = vector_at(prm, k, 1), vector_at(prm, k, 4)
        ab = b - a
        s = ti.min(ti.max((p - a).dot(ab) / ti.max(ab.dot(ab), 1e-300), 0.0), 1.0)
        out = closest_on_ball(p, a + s * ab, prm[k, 7])
    elif kind == BOX:
        centre, half = vector_at(prm, k, 1), vector_at(prm, k, 4)
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
def sample_point(x: ti.template(), nodes: ti.template(), weights: ti.template(), s):
    """Contact point s of a body at positions x: Σ uⱼ x[nⱼ] over its carrier nodes and weights."""
    n, w = nodes[s], weights[s]
    return w[0] * x[n[0]] + w[1] * x[n[1]] + w[2] * x[n[2]]


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


@ti.func
def within_ball(balls: ti.template(), k, p, reach):
    """Whether p may lie within `reach` of what ball k (centre, radius; < 0: unbounded) bounds."""
    r = balls[k, 3]
    d = p - vector_at(balls, k, 0)
    return r < 0.0 or d.dot(d) <= (r + reach) * (r + reach)


@ti.func
def within_box(boxes: ti.template(), k, col, p, reach):
    """Whether p lies within `reach` of the box in row k's columns col..col+5 (low, high corner)."""
    return within_corners(vector_at(boxes, k, col), vector_at(boxes, k, col + 3), p, reach)


@ti.func
def within_corners(lo, hi, p, reach):
    """Whether p lies within `reach` of the box with corners lo and hi."""
    d = ti.max(lo - p, p - hi, 0.0)
    return d.dot(d) <= reach * reach


@ti.func
def cell_range(lo, hi, origin, cell, dims):
    """The first and last cell (each an index per axis) of a grid that the box (lo, hi) meets,
    clamped to the grid's dims cells of size `cell` from `origin`."""
    a = ti.max(ti.cast(ti.floor((lo - origin) / cell), ti.i32), 0)
    b = ti.min(ti.cast(ti.floor((hi - origin) / cell), ti.i32), dims - 1)
    return a, b


def primitive_bounds(boxes: np.ndarray, start: int) -> np.ndarray:
    """(P, 13) rows of an obstacle's primitives (the first at index `start` among all): its box
    (6), its group's box (6) and the index past its group (1; read at a group's first primitive).
    Groups are runs of consecutive primitives whose boxes touch the previous one's, at most
    ⌈√P⌉ long: a rib's pieces, the ribs side by side (a sample beside one rib skips the others)."""
    group = np.zeros(len(boxes), int)
    size, first = int(np.ceil(np.sqrt(len(boxes)))), 0        # (first: where the current group starts)
    for k in range(1, len(boxes)):
        touch = np.all(boxes[k, :3] <= boxes[k - 1, 3:]) and np.all(boxes[k - 1, :3] <= boxes[k, 3:])
        if not touch or k - first >= size:
            first = k
        group[k] = group[k - 1] + (first == k)
    rows = np.zeros((len(boxes), 13))
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        rows[members, :6] = boxes[members]
        rows[members, 6:9] = boxes[members, :3].min(axis=0)
        rows[members, 9:12] = boxes[members, 3:].max(axis=0)
        rows[members, 12] = start + members[-1] + 1
    return rows


GRID_MIN_PRIMITIVES = 8        # an obstacle with fewer primitives has no grid: its groups do as well
# An obstacle's grid grows its cells rather than exceed this, so that its cell starts (int32, kept on
# the device beside the primitives) stay within 128 KiB however far its primitives spread beyond
# their size. (The soft–soft triangle grid's cap is another: detection.GRID_MAX_CELLS.)
PRIMITIVE_GRID_MAX_CELLS = 1 << 15


def primitive_grid(boxes: np.ndarray, first: int, at: int):
    """An obstacle's primitives binned in a uniform grid of its frame, for the samples within its
    margin of them. The margin is a fifth of the median primitive's box's largest side; a cell is
    that long too, or longer where the grid would exceed PRIMITIVE_GRID_MAX_CELLS (the margin
    stays). Each cell lists, in ascending order, the primitives whose box grown by the margin (with
    room for rounding) meets it, so a sample's cell holds every primitive within the margin of it,
    and one outside the grid none.

    Returns (meta, index): meta (9,) the grid's origin (3), cell size, dims (3), where its cell
    starts begin in the index array and the margin; index its part of that array (beginning at
    `at`): the cell starts (cells + 1, absolute) then the primitives' ids (global: the obstacle's
    first is `first`). None for fewer than GRID_MIN_PRIMITIVES primitives or an unbounded one."""
    if len(boxes) < GRID_MIN_PRIMITIVES or np.any(np.abs(boxes) >= 1e299):
        return None
    margin = float(np.median((boxes[:, 3:] - boxes[:, :3]).max(axis=1))) / 5
    grown = margin * (1.0 + 1e-4)            # (room for rounding, float32's too)
    lo, hi = boxes[:, :3] - grown, boxes[:, 3:] + grown
    origin = lo.min(axis=0)
    cell = margin
    while np.prod(np.floor((hi.max(axis=0) - origin) / cell) + 1) > PRIMITIVE_GRID_MAX_CELLS:
        cell *= 1.26
    dims = (np.floor((hi.max(axis=0) - origin) / cell) + 1).astype(np.int64)
    first_cell = np.clip(np.floor((lo - origin) / cell).astype(np.int64), 0, dims - 1)
    last_cell = np.clip(np.floor((hi - origin) / cell).astype(np.int64), 0, dims - 1)
    cells, prims = [], []
    for j, (a, b) in enumerate(zip(first_cell, last_cell)):
        i, k, m = np.meshgrid(*(np.arange(a[d], b[d] + 1) for d in range(3)), indexing="ij")
        cells.append(((i * dims[1] + k) * dims[2] + m).ravel())
        prims.append(np.full(cells[-1].size, first + j))
    cells, prims = np.concatenate(cells), np.concatenate(prims)
    order = np.argsort(cells, kind="stable")              # (each cell's primitives stay ascending)
    n_cells = int(np.prod(dims))
    starts = np.zeros(n_cells + 1, np.int64)
    np.cumsum(np.bincount(cells, minlength=n_cells), out=starts[1:])
    index = np.concatenate([at + n_cells + 1 + starts, prims[order]]).astype(np.int32)
    meta = np.r_[origin, cell, dims, at, margin]
    return meta, index
