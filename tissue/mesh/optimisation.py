"""Mesh optimisation under quality guards, the second stage of `tetrahedralize`.

Every boundary vertex lies on the surface after stuffing and stays there: the boundary is spread
over the surface by centroidal-Voronoi steps on surface samples (reaching into rims the lattice
under-samples), the boundary is smoothed along the surface and the interior toward its neighbours,
and the vertices of the worst tetrahedra move toward the apex that would make them regular. Every
move is guarded by the smallest dihedral angle of the tetrahedra around the vertex (no inversion; a
move is kept only if it raises that angle, or for spreading if it stays above 15 degrees), retried
at smaller steps. A tetrahedron with all four vertices on the boundary and an angle under 10
degrees is dropped.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .quality import signed_min_dihedral_angles
from .topology import (EDGES, OUTWARD_FACES, boundary_faces_and_owners, compact, incidence,
                       nonmanifold_vertices, tet_components, unique_edges)

if TYPE_CHECKING:
    from .closed_surface import SurfaceQueries

# Dihedral angles (degrees): the spreading of the boundary over the surface keeps every angle above
# _SPREAD_FLOOR (or where it was, if lower); a tetrahedron with all four vertices on the boundary and
# an angle under _DROP_BELOW is dropped rather than kept.
_SPREAD_FLOOR = 15.0
_DROP_BELOW = 10.0


def optimise(x: np.ndarray, tets: np.ndarray, surface: "SurfaceQueries", samples, sample_normals,
              rounds: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Spread the boundary over the surface and smooth, all under quality guards; boundary
    vertices move only to points of the surface. Tetrahedra with four vertices on the boundary
    and a dihedral angle under _DROP_BELOW are dropped."""
    topo = None
    for _ in range(rounds):
        if topo is None:
            topo = _Topology(tets, len(x))
            q = signed_min_dihedral_angles(x, tets)
            poor = topo.all_boundary[q[topo.all_boundary] < _DROP_BELOW]
            if 0 < len(poor) < len(tets):
                keep = np.ones(len(tets), dtype=bool)
                keep[poor] = False
                x, tets = compact(x, carve_nonmanifold(tets[keep], len(x)))
                topo = None
                continue
        b = topo.boundary
        x, q = _snap(x, q, topo, surface)
        # 1. Spread the boundary over the surface (a centroidal Voronoi step): it reaches into
        #    thin rims the lattice missed. Accepted where no angle falls under the spread floor.
        proposed = surface.closest(_lloyd_targets(x, topo, samples, sample_normals))
        x, q = _guarded_move(x, q, topo, b, proposed, np.minimum(_vertex_min(q, topo, b), _SPREAD_FLOOR))
        # 2. Smooth the boundary along the surface and the interior toward the neighbours' mean,
        #    where the worst angle around the vertex gets better.
        mean = _neighbour_mean(x, topo.boundary_edges)
        proposed = surface.closest(0.5 * (x[b] + mean[b]))
        x, q = _guarded_move(x, q, topo, b, proposed, _vertex_min(q, topo, b) + 1e-9)
        if len(topo.interior):
            i = topo.interior
            mean = _neighbour_mean(x, topo.edges)
            x, q = _guarded_move(x, q, topo, i, mean[i], _vertex_min(q, topo, i) + 1e-9)
        # 3. Move the vertices of the worst tetrahedra toward the apex that would make them regular.
        x, q = _improve_worst(x, q, topo, surface)
    for _ in range(3):
        topo = _Topology(tets, len(x))
        q = signed_min_dihedral_angles(x, tets)
        poor = topo.all_boundary[q[topo.all_boundary] < _DROP_BELOW]
        if len(poor) == 0 or len(poor) == len(tets):
            break
        keep = np.ones(len(tets), dtype=bool)
        keep[poor] = False
        x, tets = compact(x, carve_nonmanifold(tets[keep], len(x)))
    topo = _Topology(tets, len(x))
    x, _ = _snap(x, signed_min_dihedral_angles(x, tets), topo, surface)
    return compact(x, tets)


def _snap(x, q, topo: "_Topology", surface, floor: float = 10.0):
    """Move boundary vertices that are off the surface (exposed by a removal) onto it: full step,
    else half, else a quarter, where no angle falls under `floor` (or where it was, if lower)."""
    b = topo.boundary
    for fraction in (1.0, 0.5, 0.25):
        target = surface.closest(x[b])
        off = np.linalg.norm(target - x[b], axis=1) > 1e-9 * (1.0 + np.abs(x[b]).max())
        if not off.any():
            break
        movers = b[off]
        floors = np.minimum(_vertex_min(q, topo, movers), floor)
        x, q = _guarded_move(x, q, topo, movers, x[movers] + fraction * (target[off] - x[movers]), floors)
    return x, q


def carve_nonmanifold(tets: np.ndarray, n: int) -> np.ndarray:
    """Remove tetrahedra at boundary vertices that joined parts at a point or an edge."""
    for _ in range(20):
        faces, _ = boundary_faces_and_owners(tets)
        bad = nonmanifold_vertices(faces, n)
        if len(bad) == 0:
            return tets
        hit = np.isin(tets, bad).any(axis=1)
        label = tet_components(tets)
        sizes = np.bincount(label)
        small = hit & (sizes[label] < sizes.max())
        tets = tets[~(small if small.any() else hit)]
    return tets


def drop_specks(tets: np.ndarray, vol: np.ndarray, fraction: float = 0.02) -> np.ndarray:
    label = tet_components(tets)
    comp_vol = np.bincount(label, weights=vol)
    return comp_vol[label] >= fraction * comp_vol.max()


class _Topology:
    """What the optimisation needs to know about the connectivity, computed once per change."""

    def __init__(self, tets: np.ndarray, n: int):
        self.tets = tets
        self.faces, _ = boundary_faces_and_owners(tets)
        self.on_boundary = np.zeros(n, dtype=bool)
        self.on_boundary[self.faces.ravel()] = True
        self.boundary = np.flatnonzero(self.on_boundary)
        self.start, self.tet_of = incidence(tets, n)
        self.interior = np.flatnonzero(~self.on_boundary & (np.diff(self.start) > 0))
        self.edges = unique_edges(tets, EDGES)
        self.boundary_edges = unique_edges(self.faces, np.array([[0, 1], [1, 2], [2, 0]]))
        self.all_boundary = np.flatnonzero(self.on_boundary[tets].all(axis=1))

    def star(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tetrahedra around `vertices`, concatenated; segment starts, one per vertex)."""
        counts = self.start[vertices + 1] - self.start[vertices]
        seg = np.cumsum(counts) - counts
        idx = np.repeat(self.start[vertices] - seg, counts) + np.arange(counts.sum())
        return self.tet_of[idx], seg

    def vertex_normals(self, x: np.ndarray) -> np.ndarray:
        f = x[self.faces]
        fn = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
        vn = np.zeros_like(x)
        for c in range(3):
            np.add.at(vn, self.faces[:, c], fn)
        return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _guarded_move(x, q, topo: _Topology, movers, proposed, floor) -> tuple[np.ndarray, np.ndarray]:
    """Move `movers` to `proposed` together, then undo moves until every moved vertex has all its
    tetrahedra at quality >= its floor. Returns the new (x, q)."""
    if len(movers) == 0:
        return x, q
    tets = topo.tets
    star, seg = topo.star(movers)
    x_new = x.copy()
    x_new[movers] = proposed
    q_new = q.copy()
    changed = np.unique(star)
    moving = np.ones(len(movers), dtype=bool)
    for _ in range(100):
        q_new[changed] = signed_min_dihedral_angles(x_new, tets[changed])
        fail = moving & (np.minimum.reduceat(q_new[star], seg) < floor)
        if not fail.any():
            break
        moving &= ~fail
        back = movers[fail]
        x_new[back] = x[back]
        changed = np.unique(topo.star(back)[0])
    else:  # pragma: no cover - the moved set shrinks every round, so this is not reached
        x_new[movers[moving]] = x[movers[moving]]
        q_new[:] = q
    return x_new, q_new


def _vertex_min(q, topo: _Topology, vertices: np.ndarray) -> np.ndarray:
    star, seg = topo.star(vertices)
    return np.minimum.reduceat(q[star], seg)


def _improve_worst(x, q, topo: "_Topology", surface, below: float = 25.0):
    """For each vertex of a tetrahedron under `below` degrees, try moving it toward the apex over
    the opposite face of its worst tetrahedron that would make that tetrahedron regular (boundary
    vertices then back onto the surface); keep the moves that raise the vertex's worst angle."""
    tets = topo.tets
    poor = np.flatnonzero(q < below)
    if len(poor) == 0:
        return x, q
    verts = np.unique(tets[poor])
    star, seg = topo.star(verts)
    # The worst tetrahedron around each vertex, and the vertex's corner in it.
    qs = q[star]
    vmin = np.minimum.reduceat(qs, seg)
    is_min = qs == np.repeat(vmin, np.diff(np.r_[seg, len(star)]))
    first = np.maximum.reduceat(np.where(is_min, np.arange(len(star)), -1), seg)
    worst = tets[star[first]]
    corner = np.argmax(worst == verts[:, None], axis=1)
    face = worst[np.arange(len(verts))[:, None], OUTWARD_FACES[corner]]
    f = x[face]
    normal = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    edge = np.mean([np.linalg.norm(f[:, i] - f[:, j], axis=1) for i, j in ((0, 1), (1, 2), (2, 0))], axis=0)
    # The outward normal of the face points away from the vertex: the apex lies against it.
    apex = f.mean(axis=1) - normal * (np.sqrt(2.0 / 3.0) * edge)[:, None]
    boundary = topo.on_boundary[verts]
    for step in (0.5, 0.2):
        proposed = x[verts] + step * (apex - x[verts])
        if boundary.any():
            proposed[boundary] = surface.closest(proposed[boundary])
        x, q = _guarded_move(x, q, topo, verts, proposed, _vertex_min(q, topo, verts) + 1e-9)
    return x, q


def _neighbour_mean(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    n = len(x)
    deg = np.bincount(edges.ravel(), minlength=n).astype(np.float64)
    s = np.empty((n, 3))
    for d in range(3):
        s[:, d] = np.bincount(edges[:, 0], weights=x[edges[:, 1], d], minlength=n) + np.bincount(
            edges[:, 1], weights=x[edges[:, 0], d], minlength=n)
    return s / np.maximum(deg, 1.0)[:, None]


def _lloyd_targets(x: np.ndarray, topo: _Topology, samples, sample_normals) -> np.ndarray:
    """Centroid of the surface samples nearest to each boundary vertex among those facing the
    same way: a centroidal-Voronoi step that spreads the boundary over the whole surface, thin
    rims included. Vertices without samples keep their place."""
    from scipy.spatial import cKDTree

    b = topo.boundary
    normals = topo.vertex_normals(x)[b]
    k = min(6, len(b))
    _, near = cKDTree(x[b]).query(samples, k=k)
    near = near.reshape(len(samples), k)
    facing = np.einsum("skd,sd->sk", normals[near], sample_normals) > 0.2
    choice = np.where(facing.any(axis=1), facing.argmax(axis=1), 0)
    owner = near[np.arange(len(samples)), choice]
    count = np.bincount(owner, minlength=len(b)).astype(np.float64)
    target = x[b].copy()
    has = count > 0
    for d in range(3):
        target[has, d] = np.bincount(owner, weights=samples[:, d], minlength=len(b))[has] / count[has]
    return target
