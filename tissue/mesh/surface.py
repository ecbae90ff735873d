"""The boundary surface of a tetrahedral mesh: the faces that belong to exactly one tetrahedron.

Contact and rendering work on this surface; orienting it outward here means no later stage has to
guess which side of a triangle is the outside.
"""

from __future__ import annotations

import numpy as np

from .tetmesh import TetMesh
from .topology import boundary_faces_and_owners


def boundary_faces(tets) -> np.ndarray:
    """(k, 3) triangles, on the boundary, oriented outward (tets must be positively oriented,
    as a TetMesh's are), in the order of the tetrahedra they come from."""
    return boundary_faces_and_owners(np.asarray(tets))[0]


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
