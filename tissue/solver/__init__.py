"""Time integration: implicit Euler with matrix-free CG, and the assembled scipy reference."""

from .implicit_euler import ImplicitEuler
from .parameters import CGSettings

__all__ = ["CGSettings", "ImplicitEuler"]
