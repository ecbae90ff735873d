"""Cutting (paper §4): the compliance kept exact through topology edits by low-rank updates."""

from .compliance import CuttingCompliance

__all__ = ["CuttingCompliance"]
