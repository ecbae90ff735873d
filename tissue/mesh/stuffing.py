"""Isosurface stuffing (Labelle & Shewchuk, SIGGRAPH 2007): a body-centred-cubic lattice cut to a
closed surface, the first stage of `tetrahedralize`.

A BCC lattice of cube edge `h` covers the surface's bounding box: cube corners and centres, four
tetrahedra around each centre-to-centre edge (twelve per cube), all congruent with dihedral angles
of 60 and 90 degrees. The surface cuts lattice edges at points found by casting rays along them. A
lattice vertex closer to a cut point than 0.25 (long edges) or 0.41 (short edges) of the edge is
warped onto it. Tetrahedra inside are kept whole; those crossing the surface are cut into one to
three tetrahedra at the cut points (stencils by the signs of their vertices). Quadrilaterals are
split through their smallest global vertex id, which keeps neighbours conforming and every prism
splittable; this is not the paper's parity rule, so its 10.7-degree bound is not claimed (the
optimisation afterwards, `tissue.mesh.optimisation`, repairs the few poor tetrahedra). Where parts
thinner than the lattice touch at a warped vertex (a pinch in the boundary), that vertex is left
unwarped and the stuffing repeated, which resolves it as marching tetrahedra would, to a manifold.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .tetmesh import signed_volumes
from .topology import EDGES, boundary_faces_and_owners, compact, nonmanifold_vertices, unique_edges

if TYPE_CHECKING:
    from .closed_surface import SurfaceQueries

# A lattice vertex closer to a cut point than this fraction of the edge's length is warped onto
# it; long (axis-parallel, length h) and short (centre-to-corner, 0.87 h) edges of the BCC lattice.
_ALPHA_LONG = 0.24999
_ALPHA_SHORT = 0.41189

# Prism symmetries bringing vertex k to position 0 (prism (0,1,2)-(3,4,5), edges i - i+3).
_PRISM_ROTATIONS = np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4],
                             [3, 5, 4, 0, 2, 1], [4, 3, 5, 1, 0, 2], [5, 4, 3, 2, 1, 0]])


def stuff(surface: "SurfaceQueries", lo, hi, h: float, shift=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Isosurface stuffing (see _stuff_lattice), repeated without warping the lattice vertices
    where the result's boundary pinches (two parts touching at a warped vertex, where the shape is
    thinner than the lattice): unwarped, they resolve as in marching tetrahedra, a manifold."""
    points, tets = _bcc_lattice(lo, hi, h, shift)
    sd = surface.signed_distance(points)
    tets = tets[sd[tets].min(axis=1) < 0.0]  # only tetrahedra inside or crossing matter
    if len(tets) == 0:
        return points[:0], np.zeros((0, 4), dtype=np.int64)
    no_warp = np.zeros(len(points), dtype=bool)
    for _ in range(6):
        x, result = _stuff_lattice(surface, points, tets, sd, h, no_warp)
        faces, _ = boundary_faces_and_owners(result) if len(result) else (np.zeros((0, 3), dtype=np.int64), None)
        pinched = nonmanifold_vertices(faces, len(x))
        pinched = pinched[pinched < len(points)]  # lattice vertices (cut points come after)
        pinched = pinched[~no_warp[pinched]]
        if len(pinched) == 0:
            break
        no_warp[pinched] = True
    if len(result) == 0:
        return x[:0], result
    return compact(x, result)


def _stuff_lattice(surface: "SurfaceQueries", points, tets, sd, h: float, no_warp) -> tuple[np.ndarray, np.ndarray]:
    """Isosurface stuffing on a BCC lattice: warp lattice vertices near the surface onto it, keep
    the tetrahedra inside, and cut those crossing the surface at their edges' cut points. The
    boundary of the result is a triangulation of points on the surface. Quadrilaterals are split
    by a global vertex order (not the paper's parity rule), so the angle bound of the paper does
    not hold as such; the optimisation afterwards repairs the few poor tetrahedra."""
    n = len(points)

    # Cut points: where the surface crosses edges with a vertex strictly inside and one outside.
    edges = unique_edges(tets, EDGES)
    a, b = edges[:, 0], edges[:, 1]
    crossing = (sd[a] < 0) != (sd[b] < 0)
    crossing &= (sd[a] != 0) & (sd[b] != 0)
    edges = edges[crossing]
    inner = np.where(sd[edges[:, 0]] < 0, edges[:, 0], edges[:, 1])
    outer = np.where(sd[edges[:, 0]] < 0, edges[:, 1], edges[:, 0])
    length = np.linalg.norm(points[outer] - points[inner], axis=1)
    direction = (points[outer] - points[inner]) / length[:, None]
    t = surface.first_hit(points[inner], direction)
    fallback = ~(t <= length)
    t[fallback] = (length * -sd[inner] / (sd[outer] - sd[inner]))[fallback]
    cut = points[inner] + t[:, None] * direction
    # Warp each vertex violated by a cut point (nearer than alpha of the edge) onto the nearest one.
    alpha = np.where(length > 0.95 * h, _ALPHA_LONG, _ALPHA_SHORT) * length
    dist = np.concatenate([t, length - t])
    vertex = np.concatenate([inner, outer])
    violated = (dist < np.concatenate([alpha, alpha])) & ~no_warp[vertex]
    order = np.lexsort((dist[violated], vertex[violated]))
    vv, cv = vertex[violated][order], np.concatenate([cut, cut])[violated][order]
    first = np.ones(len(vv), dtype=bool)
    first[1:] = vv[1:] != vv[:-1]
    warped = vv[first]
    points = points.copy()
    points[warped] = cv[first]
    sign = np.sign(sd).astype(np.int64)
    sign[warped] = 0

    # Cut points that survive: edges whose endpoints still have strictly opposite signs.
    alive = (sign[edges[:, 0]] * sign[edges[:, 1]]) < 0
    edges, cut = edges[alive], cut[alive]
    edge_key = np.sort(edges, axis=1)
    edge_key = edge_key[:, 0] * n + edge_key[:, 1]
    key_order = np.argsort(edge_key)
    edge_key = edge_key[key_order]
    cut_id = n + key_order  # global id of the cut point on each (sorted) edge

    def cut_of(p, q):
        k = np.minimum(p, q) * n + np.maximum(p, q)
        return cut_id[np.searchsorted(edge_key, k)]

    # Classify tetrahedra and order each one's vertices: inside first, then on, then outside.
    s = sign[tets]
    n_in, n_on, n_out = (s < 0).sum(1), (s == 0).sum(1), (s > 0).sum(1)
    rank = np.argsort(s, axis=1, kind="stable")
    v = np.take_along_axis(tets, rank, axis=1)
    out = []
    whole = (n_in > 0) & (n_out == 0)
    out.append(tets[whole])
    all_on = n_on == 4
    if all_on.any():
        inside = surface.signed_distance(points[tets[all_on]].mean(axis=1)) < 0
        out.append(tets[all_on][inside])
    sel = (n_in == 1) & (n_out == 3)
    w = v[sel]
    out.append(np.stack([w[:, 0], cut_of(w[:, 0], w[:, 1]), cut_of(w[:, 0], w[:, 2]),
                         cut_of(w[:, 0], w[:, 3])], 1))
    sel = (n_in == 1) & (n_on == 1) & (n_out == 2)
    w = v[sel]
    out.append(np.stack([w[:, 0], w[:, 1], cut_of(w[:, 0], w[:, 2]), cut_of(w[:, 0], w[:, 3])], 1))
    sel = (n_in == 1) & (n_on == 2) & (n_out == 1)
    w = v[sel]
    out.append(np.stack([w[:, 0], w[:, 1], w[:, 2], cut_of(w[:, 0], w[:, 3])], 1))
    sel = (n_in == 2) & (n_out == 2)
    w = v[sel]
    out.append(_split_prisms(np.stack([w[:, 0], cut_of(w[:, 0], w[:, 2]), cut_of(w[:, 0], w[:, 3]),
                                       w[:, 1], cut_of(w[:, 1], w[:, 2]), cut_of(w[:, 1], w[:, 3])], 1)))
    sel = (n_in == 3) & (n_out == 1)
    w = v[sel]
    out.append(_split_prisms(np.stack([w[:, 0], w[:, 1], w[:, 2], cut_of(w[:, 0], w[:, 3]),
                                       cut_of(w[:, 1], w[:, 3]), cut_of(w[:, 2], w[:, 3])], 1)))
    sel = (n_in == 2) & (n_on == 1) & (n_out == 1)
    w = v[sel]
    # A pyramid: apex the on vertex, base (i1, i2, c2, c1) split through its smallest id.
    i1, i2, z = w[:, 0], w[:, 1], w[:, 2]
    c1, c2 = cut_of(i1, w[:, 3]), cut_of(i2, w[:, 3])
    diag = np.minimum(i1, c2) < np.minimum(i2, c1)
    out.append(np.where(diag[:, None], np.stack([z, i1, i2, c2], 1), np.stack([z, i1, i2, c1], 1)))
    out.append(np.where(diag[:, None], np.stack([z, i1, c2, c1], 1), np.stack([z, i2, c2, c1], 1)))

    result = np.concatenate(out).astype(np.int64)
    all_points = np.concatenate([points, cut[key_order]]) if len(cut) else points
    vol = signed_volumes(all_points, result)
    flip = vol < 0
    result[flip, 2], result[flip, 3] = result[flip, 3].copy(), result[flip, 2].copy()
    # Tetrahedra flattened by warping (all four vertices on a locally flat surface) are dropped.
    edge_vec = all_points[result[:, [1, 2, 3, 2, 3, 3]]] - all_points[result[:, [0, 0, 0, 1, 1, 2]]]
    longest = np.sqrt((edge_vec ** 2).sum(-1).max(axis=1))
    return all_points, result[np.abs(vol) > 1e-6 * longest ** 3]


def _bcc_lattice(lo: np.ndarray, hi: np.ndarray, h: float,
                 shift=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Points and positively oriented tetrahedra of a BCC lattice of cube edge h covering [lo, hi]
    with at least one cube of margin."""
    n = np.ceil((hi - lo) / h).astype(np.int64) + 3  # cubes per axis
    origin = 0.5 * (lo + hi) - 0.5 * h * n + h * np.asarray(shift, dtype=np.float64)
    nx, ny, nz = (int(v) for v in n)
    corner = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    centre = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1)
    points = np.concatenate([corner.reshape(-1, 3) * h, (centre.reshape(-1, 3) + 0.5) * h]) + origin
    n_corner = (nx + 1) * (ny + 1) * (nz + 1)

    def corner_id(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    def centre_id(i, j, k):
        return n_corner + (i * ny + j) * nz + k

    tets = []
    for axis in range(3):
        # Pairs of cubes adjacent along `axis`: the cube at index c and the one at c + e_axis.
        shape = [nx, ny, nz]
        shape[axis] -= 1
        idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
        e = np.zeros(3, dtype=np.int64)
        e[axis] = 1
        a = centre_id(*idx.T)
        b = centre_id(*(idx + e).T)
        # The square face between them lies at corner index c + e_axis; u, v span it.
        u = np.zeros(3, dtype=np.int64)
        v = np.zeros(3, dtype=np.int64)
        u[(axis + 1) % 3] = 1
        v[(axis + 2) % 3] = 1
        base = idx + e
        square = [base, base + u, base + u + v, base + v]
        for s in range(4):
            p = corner_id(*square[s].T)
            q = corner_id(*square[(s + 1) % 4].T)
            tets.append(np.stack([a, b, p, q], axis=1))
    tets = np.concatenate(tets)
    flip = signed_volumes(points, tets) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return points, tets


def _split_prisms(v: np.ndarray) -> np.ndarray:
    """Three tetrahedra for each prism (v0, v1, v2)-(v3, v4, v5), each quadrilateral face split by
    the diagonal through its smallest global id, so neighbours agree (Dompierre et al. 1999)."""
    v = v[np.arange(len(v))[:, None], _PRISM_ROTATIONS[np.argmin(v, axis=1)]]
    a = np.minimum(v[:, 1], v[:, 5]) < np.minimum(v[:, 2], v[:, 4])
    first = np.where(a[:, None], v[:, [0, 1, 2, 5]], v[:, [0, 1, 2, 4]])
    second = np.where(a[:, None], v[:, [0, 1, 5, 4]], v[:, [0, 4, 2, 5]])
    third = v[:, [0, 4, 5, 3]]
    return np.concatenate([first, second, third])
