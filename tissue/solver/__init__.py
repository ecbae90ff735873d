"""Time integration: implicit Euler with matrix-free CG, and the assembled scipy reference."""

from .implicit_euler import CGSettings, ImplicitEuler

__all__ = ["CGSettings", "ImplicitEuler"]
