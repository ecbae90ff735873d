"""Cutting (paper §4): the compliance kept exact through topology edits by low-rank updates, and
the cut itself: the swept surface, the split with its quality bound, the sides separated
(`Cutter`); the scene layer is tissue.cutting.layer (`Cut`)."""

from .compliance import CuttingCompliance
from .cutter import Cutter, CutReport
from .surface import CutPath, CutSurface

__all__ = ["CuttingCompliance", "Cutter", "CutReport", "CutPath", "CutSurface"]
