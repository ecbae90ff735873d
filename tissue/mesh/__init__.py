"""Tetrahedral meshes: validated arrays, file formats, generators, surfaces and quality."""

from .io import PvdSeries, read_mesh, write_vtu
from .quality import aspect_ratios, dihedral_angles, min_dihedral_angles, summary
from .shapes import beam, box
from .surface import boundary_faces, boundary_surface, is_watertight_oriented
from .tetmesh import TetMesh

__all__ = [
    "TetMesh",
    "read_mesh", "write_vtu", "PvdSeries",
    "box", "beam",
    "boundary_faces", "boundary_surface", "is_watertight_oriented",
    "dihedral_angles", "min_dihedral_angles", "aspect_ratios", "summary",
]
