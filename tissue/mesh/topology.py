"""Connectivity of tetrahedral meshes and triangle surfaces, vectorised in numpy: boundary faces,
unique edges, the tetrahedra around each vertex, connected components, non-manifold vertices.

Everything is found by grouping equal sorted index rows (`group_rows`): two tetrahedra share a face
exactly when their sorted vertex triples are equal.
"""

from __future__ import annotations

import numpy as np

# The four faces of a positively oriented tetrahedron (0, 1, 2, 3), row i opposite vertex i, each
# ordered so that its right-hand normal points away from that vertex, i.e. out of the tetrahedron.
OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
# The six edges of a tetrahedron.
EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def group_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group equal rows of a sorted-within-row integer array: (order, group_start) such that
    rows[order[group_start[g]:group_start[g + 1]]] are the members of group g."""
    rows = rows.astype(np.int64)
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    n = int(rows.max()) + 1
    if n ** rows.shape[1] < 2 ** 62:
        key = rows[:, 0]
        for j in range(1, rows.shape[1]):
            key = key * n + rows[:, j]
        order = np.argsort(key, kind="stable")
        k = key[order]
        new = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    else:  # pragma: no cover - only for lattices of more than a million points
        order = np.lexsort(rows.T[::-1])
        r = rows[order]
        new = np.flatnonzero(np.r_[True, np.any(r[1:] != r[:-1], axis=1)])
    return order, np.r_[new, len(rows)]


def boundary_faces_and_owners(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary faces (k, 3), oriented outward, and the tetrahedron each belongs to."""
    faces = tets[:, OUTWARD_FACES].reshape(-1, 3)
    order, start = group_rows(np.sort(faces, axis=1))
    single = order[start[:-1][np.diff(start) == 1]]
    single.sort()
    return faces[single], single // 4


def incidence(tets: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR vertex -> tetrahedra: tetrahedra of vertex v are tet_of[start[v]:start[v + 1]]."""
    flat = tets.ravel()
    order = np.argsort(flat, kind="stable")
    start = np.zeros(n_points + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=n_points), out=start[1:])
    return start, order // 4


def unique_edges(cells: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    e = np.sort(cells[:, pairs].reshape(-1, 2), axis=1)
    order, start = group_rows(e)
    return e[order[start[:-1]]]


def nonmanifold_vertices(faces: np.ndarray, n_points: int) -> np.ndarray:
    """Vertices where a closed triangle surface is not a manifold: an edge there is shared by
    more than two triangles, or the triangles around the vertex form more than one fan."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    k = len(faces)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    # Edge uses: use 3f + j is the edge from corner j to corner j + 1 of face f.
    ends = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    order, start = group_rows(np.sort(ends, axis=1))
    size = np.diff(start)
    bad = [np.unique(ends[order[start[:-1][size > 2]]])]
    first, second = order[start[:-1][size == 2]], order[start[:-1][size == 2] + 1]
    # Link the corners of the two faces that hold the same vertex (incidence id = 3f + corner).
    f1, j1 = first // 3, first % 3
    f2, j2 = second // 3, second % 3
    same = faces[f1, j1] == faces[f2, j2]
    a0, a1 = 3 * f1 + j1, 3 * f1 + (j1 + 1) % 3
    b0, b1 = 3 * f2 + j2, 3 * f2 + (j2 + 1) % 3
    rows = np.concatenate([a0, a1])
    cols = np.concatenate([np.where(same, b0, b1), np.where(same, b1, b0)])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * k, 3 * k))
    _, label = connected_components(graph, directed=False)
    vertex = faces.ravel()
    order, start = group_rows(np.stack([vertex, label], axis=1))
    fans = np.bincount(vertex[order[start[:-1]]], minlength=n_points)
    bad.append(np.flatnonzero(fans > 1))
    return np.unique(np.concatenate(bad))


def tet_components(tets: np.ndarray) -> np.ndarray:
    """Component label of each tetrahedron (connected through shared faces)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    order, start = group_rows(np.sort(tets[:, OUTWARD_FACES].reshape(-1, 3), axis=1))
    pairs = start[:-1][np.diff(start) == 2]
    a, b = order[pairs] // 4, order[pairs + 1] // 4
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(tets), len(tets)))
    return connected_components(graph, directed=False)[1]


def compact(x: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inverse = np.unique(tets.ravel(), return_inverse=True)
    return x[used], inverse.reshape(tets.shape)
