"""Splitting tetrahedra along a cut, and the quality bound on what the split creates.

Each node near the cut has a state: +1 or −1 (its side of the cut surface) or 0 (on the cut: a
node within SNAP of the local edge length from the surface is snapped onto it; the cut surface is
bent through the node, the mesh does not move). An element with a + and a − node whose every
+/− edge crosses the surface is split by the plane of its cut points: one new node on each +/−
edge (shared by every element around that edge), and the element's + side and − side, two convex
pieces (a tetrahedron, pyramid or prism each), are cut into tetrahedra.

Why this subdivision (and not Mor & Kanade's progressive one): the piece of each side is convex,
and it is cut into tetrahedra by the minimum-index rule (every polygonal face fanned from its
lowest node id, the piece coned from its lowest node id), which two elements sharing a face apply
alike, so the result is conforming without case tables; and the only elements it creates have
corners at original nodes and at cut points inside their edges, so their quality is bounded
(below) by how far the cut points stay from the ends of the edges. An element the cut has only
partly crossed (the crack front) is not split; a cut point on an edge it shares with elements
that are split is snapped to the nearer end of the edge (so no element has a hanging node), and
a node once on the cut stays on it. A cut advanced in small steps therefore runs mostly along
faces through snapped nodes, splitting the elements crossed whole within one step: the cut
advances behind the blade at once, and its surface is as fine as the mesh.

The quality bound. Every tetrahedron a cut creates has a smallest dihedral angle of at least
MIN_DIHEDRAL degrees and a condition number (Knupp's ‖S‖ ‖S⁻¹‖ / 3 of its edge matrix relative
to the regular tetrahedron: 1 for a regular one, unbounded for a flat one) of at most
MAX_CONDITION. Snapping (cut points at least SNAP of an edge from its ends) makes a violation
rare; the cutter enforces the bound by snapping the cut points of any element that violates it
onto the nearer end of their edge and splitting again, until none does: snapping only removes
cut points, and with none left the cut runs along existing faces (elements are separated, not
split), so the loop ends with every created element within the bound.
"""

from __future__ import annotations

import numpy as np

from ..mesh.quality import min_dihedral_angles
from ..mesh.tetmesh import signed_volumes

MIN_DIHEDRAL = 5.0          # degrees
MAX_CONDITION = 25.0        # Knupp's condition number (1: regular tetrahedron)
SNAP = 0.2                  # fraction of an edge within which a cut point snaps to its end

# A regular tetrahedron's edge matrix (unit edges), the reference of the condition number.
_REGULAR_INVERSE = np.linalg.inv(np.array([[1.0, 0.5, 0.5],
                                           [0.0, np.sqrt(3.0) / 2.0, np.sqrt(3.0) / 6.0],
                                           [0.0, 0.0, np.sqrt(2.0 / 3.0)]]))
_FACES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))          # as cycles (orientation set later)
_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def condition_numbers(points, tets) -> np.ndarray:
    """Knupp's condition number of each tetrahedron: ‖S‖_F ‖S⁻¹‖_F / 3 with S its edge matrix
    mapped from the regular tetrahedron; inf for a flat one."""
    p = np.asarray(points, np.float64)[np.asarray(tets)]
    S = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2) @ _REGULAR_INVERSE
    out = np.full(len(S), np.inf)
    ok = np.abs(np.linalg.det(S)) > 1e-300
    if ok.any():
        out[ok] = np.linalg.norm(S[ok], axis=(1, 2)) * np.linalg.norm(np.linalg.inv(S[ok]), axis=(1, 2)) / 3.0
    return out


def quality(points, tets) -> tuple[float, float]:
    """(worst smallest dihedral angle in degrees, worst condition number) of these tetrahedra;
    (inf, 1) for none; a flat or inverted one counts as (0, inf)."""
    tets = np.asarray(tets).reshape(-1, 4)
    if len(tets) == 0:
        return float("inf"), 1.0
    volumes = signed_volumes(np.asarray(points, np.float64), tets)
    if (volumes <= 0).any():
        return 0.0, float("inf")
    return float(min_dihedral_angles(points, tets).min()), float(condition_numbers(points, tets).max())


def within_bound(points, tets) -> np.ndarray:
    """(k,) bool: positive and within the quality bound (MIN_DIHEDRAL, MAX_CONDITION)."""
    tets = np.asarray(tets).reshape(-1, 4)
    ok = signed_volumes(np.asarray(points, np.float64), tets) > 0
    if ok.any():
        good = (min_dihedral_angles(points, tets[ok]) >= MIN_DIHEDRAL) & \
               (condition_numbers(points, tets[ok]) <= MAX_CONDITION)
        ok[np.flatnonzero(ok)] = good
    return ok


def _fan(cycle) -> list[tuple[int, int, int]]:
    """A convex polygon (node ids in cyclic order) fanned from its lowest id."""
    k = int(np.argmin(cycle))
    c = list(cycle[k:]) + list(cycle[:k])
    return [(c[0], c[i], c[i + 1]) for i in range(1, len(c) - 1)]


def _cut_polygon(ids, rest, normal):
    """The cut points and on-cut nodes of an element in cyclic order around `normal`."""
    p = rest[ids]
    centre = p.mean(axis=0)
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    angle = np.arctan2((p - centre) @ w, (p - centre) @ u)
    return [ids[i] for i in np.argsort(angle)]


def split_element(nodes, states, cut_points: dict, rest: np.ndarray):
    """Split one element (4 node ids, their states ±1 / 0) along its cut. cut_points: {(a, b)
    sorted node ids: new node id} for its +/− edges; rest: positions of every node id (new ones
    too). Returns (sub-tetrahedra (k, 4) positively oriented, their sides (k,) ±1, the cut
    triangles (c, 3) between the two sides)."""
    nodes, states = [int(n) for n in nodes], [int(s) for s in states]
    cut = {}
    for i, j in _EDGES:
        if states[i] * states[j] < 0:
            cut[(i, j)] = cut[(j, i)] = cut_points[(min(nodes[i], nodes[j]), max(nodes[i], nodes[j]))]
    on_cut = [nodes[i] for i in range(4) if states[i] == 0] + sorted(set(cut.values()))
    plus = rest[[nodes[i] for i in range(4) if states[i] > 0]].mean(axis=0)
    minus = rest[[nodes[i] for i in range(4) if states[i] < 0]].mean(axis=0)
    normal = (plus - minus) / np.linalg.norm(plus - minus)
    cut_cycle = _cut_polygon(on_cut, rest, normal)
    cut_triangles = _fan(cut_cycle)
    tets, sides = [], []
    for side in (1, -1):
        faces = [cut_triangles]
        for face in _FACES:
            cycle = []
            for k, i in enumerate(face):
                j = face[(k + 1) % 3]
                if states[i] in (side, 0):
                    cycle.append(nodes[i])
                if (i, j) in cut:
                    cycle.append(cut[(i, j)])
            if len(cycle) >= 3:
                faces.append(_fan(cycle))
        apex = min(n for tri in faces for t in tri for n in t)
        for tri in faces:
            tets += [(apex, *t) for t in tri if apex not in t]
            sides += [side] * sum(apex not in t for t in tri)
    tets = np.array(tets, dtype=np.int64).reshape(-1, 4)
    flip = signed_volumes(rest, tets) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return tets, np.array(sides, dtype=np.int64), np.array(cut_triangles, dtype=np.int64).reshape(-1, 3)
