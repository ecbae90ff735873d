"""TetMesh: a tetrahedral mesh as validated numpy arrays.

Every mesh that enters the simulator passes through `TetMesh(...)`, so every later stage may assume
finite coordinates, indices in range, no degenerate tetrahedron and positive orientation
(det[x1-x0, x2-x0, x3-x0] > 0). Inverted tetrahedra are re-oriented with a warning; degenerate ones
are refused, naming their ids.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import TissueError

# A tetrahedron whose volume is below this fraction of its edge length cubed is degenerate
# (a regular tetrahedron has V / l^3 = 0.118).
DEGENERATE_RELATIVE_VOLUME = 1e-8


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron, positive when (x1-x0, x2-x0, x3-x0) is right-handed."""
    p = points[tets]
    d = p[:, 1:] - p[:, :1]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def _ids(ids: np.ndarray, limit: int = 10) -> str:
    shown = ", ".join(str(i) for i in ids[:limit])
    return shown + (f", ... ({len(ids)} in all)" if len(ids) > limit else "")


@dataclass(frozen=True)
class TetMesh:
    """Points (n, 3) float64 and tetrahedra (m, 4) int32, validated on construction.

    `source` names where the mesh came from (a file path or a generator) for error messages.
    """

    points: np.ndarray
    tets: np.ndarray
    source: str = "mesh"
    _volumes: np.ndarray = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        src = self.source
        points = np.asarray(self.points, dtype=np.float64)
        tets = np.asarray(self.tets)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise TissueError(f"{src}: points must be a non-empty (n, 3) array, got shape {points.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
            raise TissueError(f"{src}: tetrahedra must be a non-empty (m, 4) array, got shape {tets.shape}"
                              " (is this a surface mesh? a volume mesh is needed)")
        if not np.issubdtype(tets.dtype, np.integer):
            if not np.all(np.equal(np.mod(tets, 1), 0)):
                raise TissueError(f"{src}: tetrahedron indices must be integers")
        tets = tets.astype(np.int64)
        bad_pts = np.flatnonzero(~np.isfinite(points).all(axis=1))
        if len(bad_pts):
            raise TissueError(f"{src}: non-finite coordinates at points {_ids(bad_pts)}")
        bad = np.flatnonzero(((tets < 0) | (tets >= len(points))).any(axis=1))
        if len(bad):
            raise TissueError(f"{src}: tetrahedra {_ids(bad)} index points out of range [0, {len(points)})")
        repeated = np.flatnonzero(np.sort(tets, axis=1)[:, 1:] == np.sort(tets, axis=1)[:, :-1])
        vol = signed_volumes(points, tets)
        edges = points[tets[:, [1, 2, 3, 2, 3, 3]]] - points[tets[:, [0, 0, 0, 1, 1, 2]]]
        longest = np.sqrt((edges ** 2).sum(-1).max(axis=1))
        degenerate = np.union1d(np.flatnonzero(np.abs(vol) <= DEGENERATE_RELATIVE_VOLUME * longest ** 3),
                                np.unique(repeated // 3) if len(repeated) else [])
        if len(degenerate):
            raise TissueError(f"{src}: degenerate (zero-volume) tetrahedra {_ids(degenerate.astype(int))}")
        inverted = np.flatnonzero(vol < 0)
        if len(inverted):
            warnings.warn(f"{src}: re-oriented {len(inverted)} inverted tetrahedra ({_ids(inverted)})",
                          stacklevel=3)
            tets = tets.copy()
            tets[inverted, 2], tets[inverted, 3] = tets[inverted, 3].copy(), tets[inverted, 2].copy()
            vol = np.abs(vol)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tets", tets.astype(np.int32))
        object.__setattr__(self, "_volumes", vol)

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @property
    def volumes(self) -> np.ndarray:
        """Positive volume of each tetrahedron."""
        return self._volumes

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)

    def transformed(self, rotation=None, translation=None, scale: float = 1.0) -> "TetMesh":
        """A copy moved rigidly (and uniformly scaled): x -> scale * R x + t."""
        pts = self.points * scale
        if rotation is not None:
            pts = pts @ np.asarray(rotation, dtype=np.float64).T
        if translation is not None:
            pts = pts + np.asarray(translation, dtype=np.float64)
        return TetMesh(pts, self.tets, source=self.source)
