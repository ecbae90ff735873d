"""Procedural tetrahedral meshes: boxes and beams on a regular grid.

Each grid cube is cut into the 6 tetrahedra of the Kuhn (Freudenthal) split, all sharing the
cube's main diagonal. Every cube is cut the same way, so the diagonals of shared faces agree and
neighbouring cubes conform without any per-cube bookkeeping.
"""

from __future__ import annotations

import numpy as np

from ..errors import TissueError
from .tetmesh import TetMesh

# Cube corners are numbered by bits: +x = 1, +y = 2, +z = 4, so corner 7 is opposite corner 0.
# Each tetrahedron walks 0 -> one axis -> two axes -> 7, one walk per permutation of (x, y, z);
# the walks of odd permutations have their last two corners swapped so every tet is positive.
KUHN_TETS = np.array([
    [0, 1, 3, 7],   # x y z
    [0, 1, 7, 5],   # x z y (odd)
    [0, 2, 7, 3],   # y x z (odd)
    [0, 2, 6, 7],   # y z x
    [0, 4, 5, 7],   # z x y
    [0, 4, 7, 6],   # z y x (odd)
])


def box(size=(1.0, 1.0, 1.0), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """The box [origin, origin + size] on a grid of cells = (nx, ny, nz) cubes.

    (nx+1)(ny+1)(nz+1) nodes, numbered with z fastest: node (i, j, k) is
    (i * (ny+1) + j) * (nz+1) + k; 6 nx ny nz positively oriented tetrahedra.
    """
    size = np.asarray(size, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    source = f"box(size={size.tolist()}, cells={np.asarray(cells).tolist()})"
    if size.shape != (3,) or not np.all(np.isfinite(size) & (size > 0)):
        raise TissueError(f"{source}: size must be three positive lengths")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise TissueError(f"{source}: origin must be three finite coordinates")
    if np.shape(cells) != (3,) or not all(float(c).is_integer() and c >= 1 for c in cells):
        raise TissueError(f"{source}: cells must be three positive integers")
    nx, ny, nz = (int(c) for c in cells)

    axes = [np.linspace(origin[a], origin[a] + size[a], n + 1) for a, n in enumerate((nx, ny, nz))]
    points = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    node = np.arange(len(points)).reshape(nx + 1, ny + 1, nz + 1)
    # corners[c] lists corner c of every cube, in the same cube order for all 8 corners.
    corners = np.stack([node[c & 1:nx + (c & 1), (c >> 1) & 1:ny + ((c >> 1) & 1), c >> 2:nz + (c >> 2)].ravel()
                        for c in range(8)])
    tets = corners[KUHN_TETS].transpose(2, 0, 1).reshape(-1, 4)
    return TetMesh(points, tets, source=source)


def beam(length: float, width: float, height: float, cells_along: int, cells_across) -> TetMesh:
    """A beam along +x: x in [0, length] (x = 0 is the end to clamp), y in [-width/2, width/2],
    z in [-height/2, height/2].

    `cells_across` is the number of cells across the section, one int for both y and z or a
    pair (cells along y, cells along z).
    """
    across = np.broadcast_to(np.asarray(cells_across), (2,))
    return box(size=(length, width, height), cells=(cells_along, *across.tolist()),
               origin=(0.0, -width / 2.0, -height / 2.0))
