"""Element quality: small dihedral angles and large aspect ratios make linear tetrahedra stiff and
ill-conditioned, so a mesh is worth checking before it is simulated.

Both measures take (points, tets) so they apply to deformed configurations too; they are meant for
non-degenerate tetrahedra (a flat one has aspect ratio inf).
"""

from __future__ import annotations

import numpy as np

from .tetmesh import TetMesh, signed_volumes
from .topology import OUTWARD_FACES

# The faces (rows of OUTWARD_FACES) meeting at each of the six edges: faces opposite vertices
# k and l meet along the edge between the other two vertices.
FACE_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def _face_normals(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m, 4, 3) outward normals whose length is twice the face area, face i opposite vertex i."""
    p = points[tets[:, OUTWARD_FACES]]
    return np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])


def dihedral_angles(points, tets) -> np.ndarray:
    """(m, 6) interior dihedral angles in degrees, one per edge: pi minus the angle between the
    outward normals of the two faces meeting at that edge."""
    points, tets = np.asarray(points, dtype=np.float64), np.asarray(tets)
    n = _face_normals(points, tets)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cos = -np.einsum("mij,mij->mi", n[:, FACE_PAIRS[:, 0]], n[:, FACE_PAIRS[:, 1]])
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def min_dihedral_angles(points, tets) -> np.ndarray:
    """Smallest dihedral angle of each tetrahedron in degrees (70.53 for a regular one, -> 0 for
    slivers, needles and caps)."""
    return dihedral_angles(points, tets).min(axis=1)


def signed_min_dihedral_angles(points, tets) -> np.ndarray:
    """Smallest dihedral angle of each tetrahedron in degrees, less 180 where it is inverted or
    flat (< 0): the one number a mesh optimiser's guards compare, so a flat tetrahedron's zero
    normals count as 0 rather than NaN (which every comparison would let through)."""
    n = _face_normals(points, tets)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    cos = -np.einsum("mij,mij->mi", n[:, FACE_PAIRS[:, 0]], n[:, FACE_PAIRS[:, 1]])
    angle = np.degrees(np.arccos(np.clip(cos.max(axis=1), -1.0, 1.0)))
    return np.where(signed_volumes(points, tets) > 0, angle, angle - 180.0)


def aspect_ratios(points, tets) -> np.ndarray:
    """Radius ratio R / (3 r) of each tetrahedron, circumradius R over inradius r: 1 for a regular
    tetrahedron, growing without bound as it degenerates (it catches slivers, unlike edge ratios)."""
    points, tets = np.asarray(points, dtype=np.float64), np.asarray(tets)
    p = points[tets]
    b, c, d = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    six_volume = signed_volumes(points, tets) * 6.0
    # Circumcentre relative to vertex 0 (the point equidistant from all four vertices).
    centre = ((b ** 2).sum(1)[:, None] * np.cross(c, d) + (c ** 2).sum(1)[:, None] * np.cross(d, b)
              + (d ** 2).sum(1)[:, None] * np.cross(b, c))
    with np.errstate(divide="ignore", invalid="ignore"):
        circumradius = np.linalg.norm(centre, axis=1) / np.abs(2.0 * six_volume)
        area = 0.5 * np.linalg.norm(_face_normals(points, tets), axis=-1).sum(axis=1)
        inradius = 0.5 * np.abs(six_volume) / area  # r = 3 V / total face area
        return circumradius / (3.0 * inradius)


def summary(mesh: TetMesh) -> dict:
    """Counts, volume and the quality figures worth printing for a mesh."""
    dihedral = min_dihedral_angles(mesh.points, mesh.tets)
    aspect = aspect_ratios(mesh.points, mesh.tets)
    return {
        "n_points": mesh.n_points,
        "n_tets": mesh.n_tets,
        "volume": float(mesh.volumes.sum()),
        "min_dihedral_deg": float(dihedral.min()),
        "median_dihedral_deg": float(np.median(dihedral)),
        "max_aspect_ratio": float(aspect.max()),
        "median_aspect_ratio": float(np.median(aspect)),
    }
