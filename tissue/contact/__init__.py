"""Contact layer: the frictional contact (Coulomb cone) solver."""

from .frictional_contact import (ContactInfo, FrictionalContactSolver, natural_map_residual,
                                 solve_frictional_contact)

__all__ = ["ContactInfo", "FrictionalContactSolver", "natural_map_residual", "solve_frictional_contact"]
