"""Tetrahedral meshes: validated arrays, file formats, generators, surfaces and quality."""

from .tetmesh import TetMesh

__all__ = ["TetMesh"]
