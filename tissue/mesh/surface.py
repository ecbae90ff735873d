"""The boundary surface of a tetrahedral mesh: the faces that belong to exactly one tetrahedron.

Contact and rendering work on this surface; orienting it outward here means no later stage has to
guess which side of a triangle is the outside.
"""

from __future__ import annotations

import numpy as np

from .tetmesh import TetMesh

# The four faces of a positively oriented tetrahedron (0, 1, 2, 3), row i opposite vertex i, each
# ordered so that its right-hand normal points away from that vertex, i.e. out of the tetrahedron.
OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def boundary_faces(tets) -> np.ndarray:
    """(k, 3) triangles, on the boundary, oriented outward (tets must be positively oriented,
    as a TetMesh's are), in the order of the tetrahedra they come from."""
    tets = np.asarray(tets)
    faces = tets[:, OUTWARD_FACES].reshape(-1, 3)
    # Two tets share a face exactly when the sorted vertex triples are equal: sort the triples,
    # group equal rows, keep the groups of one.
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    new_group = np.ones(len(order) + 1, dtype=bool)
    new_group[1:-1] = np.any(key[order[1:]] != key[order[:-1]], axis=1)
    starts = np.flatnonzero(new_group)
    single = starts[:-1][np.diff(starts) == 1]
    return faces[np.sort(order[single])].astype(tets.dtype)


def boundary_surface(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertex_ids, faces): the mesh points on the boundary, and the boundary triangles indexing
    into `vertex_ids` (so `mesh.points[vertex_ids]` with `faces` is a standalone surface)."""
    faces = boundary_faces(mesh.tets)
    vertex_ids = np.unique(faces)
    return vertex_ids, np.searchsorted(vertex_ids, faces).astype(np.int32)


def is_watertight_oriented(faces) -> bool:
    """True when every edge is shared by exactly two faces that traverse it in opposite
    directions: the surface is closed, manifold along its edges, and consistently oriented."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    n = int(faces.max()) + 1 if len(faces) else 0
    directed = np.sort(edges[:, 0] * n + edges[:, 1])
    reversed_ = np.sort(edges[:, 1] * n + edges[:, 0])
    # Each directed edge used once, and its reverse present: the two sets are equal.
    return bool(len(faces)) and bool(np.all(directed[1:] != directed[:-1])) and np.array_equal(directed, reversed_)
