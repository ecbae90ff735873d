"""A surface embedded in a tetrahedral mesh: each surface point follows the tetrahedron it lies in.

This is SOFA's visual model with a barycentric mapping: the mechanics run on a coarse tetrahedral
mesh, and what is drawn is the smooth surface the mesh was made from, carried along by the
mesh's deformation. Points outside every tetrahedron (a mesh's boundary cuts corners off a smooth
surface) use the nearest tetrahedron's affine map, extrapolated.
"""

from __future__ import annotations

import numpy as np

from ..errors import TissueError


class EmbeddedSurface:
    """Triangles whose points are affine combinations of a tetrahedral mesh's nodes."""

    def __init__(self, surface_points, triangles, mesh_points, tets, candidates: int = 16):
        from scipy.spatial import cKDTree

        points = np.asarray(surface_points, dtype=np.float64)
        mesh_points = np.asarray(mesh_points, dtype=np.float64)
        tets = np.asarray(tets, dtype=np.int64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise TissueError(f"embedding: surface points must be a non-empty (n, 3) array, got {points.shape}")
        corners = mesh_points[tets]                       # (m, 4, 3)
        centroids = corners.mean(axis=1)
        k = min(candidates, len(tets))
        _, nearest = cKDTree(centroids).query(points, k=k)
        nearest = nearest.reshape(len(points), k)
        weights = self._barycentric(points, corners, nearest)     # (n, k, 4)
        # The most-inside candidate: the largest smallest weight (>= 0 inside its tetrahedron).
        best = np.argmax(weights.min(axis=2), axis=1)
        rows = np.arange(len(points))
        self.tet_of_point = nearest[rows, best]
        self.weights = weights[rows, best]                        # (n, 4), sum to 1
        self.nodes = tets[self.tet_of_point]                      # (n, 4)

    @staticmethod
    def _barycentric(points, corners, candidates):
        c = corners[candidates]                                   # (n, k, 4, 3)
        edges = np.stack([c[:, :, i] - c[:, :, 0] for i in (1, 2, 3)], axis=-1)   # (n, k, 3, 3)
        rhs = points[:, None, :] - c[:, :, 0]
        local = np.linalg.solve(edges, rhs[..., None])[..., 0]                   # (n, k, 3)
        return np.concatenate([1.0 - local.sum(axis=-1, keepdims=True), local], axis=-1)

    def points(self, mesh_positions) -> np.ndarray:
        """The surface points for the mesh's nodes at `mesh_positions` (n_nodes, 3)."""
        x = np.asarray(mesh_positions, dtype=np.float64)
        return np.einsum("pk,pkd->pd", self.weights, x[self.nodes])

    def values(self, nodal_values) -> np.ndarray:
        """Per-node scalars of the mesh interpolated to the surface points."""
        v = np.asarray(nodal_values, dtype=np.float64)
        return np.einsum("pk,pk->p", self.weights, v[self.nodes])
