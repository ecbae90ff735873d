"""Finite elements: materials and co-rotational linear tetrahedra."""

from .corotational import ACCUMULATIONS, ROTATIONS, CorotationalFEM
from .material import Material

__all__ = ["ACCUMULATIONS", "ROTATIONS", "CorotationalFEM", "Material"]
