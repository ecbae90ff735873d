"""Isotropic linear elastic material (Young's modulus, Poisson ratio, density)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import TissueError


@dataclass(frozen=True)
class Material:
    young: float = 3000.0      # Pa
    poisson: float = 0.3
    density: float = 1000.0    # kg/m^3

    def __post_init__(self):
        for name in ("young", "poisson", "density"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise TissueError(f"{name}: must be a finite number, got {value!r}")
        if self.young <= 0:
            raise TissueError(f"young: Young's modulus must be > 0 Pa, got {self.young!r}")
        if not -1.0 < self.poisson < 0.5:
            raise TissueError(f"poisson: Poisson ratio must lie in (-1, 0.5), got {self.poisson!r}"
                              " (0.5 is incompressible, which linear tetrahedra cannot represent)")
        if self.density <= 0:
            raise TissueError(f"density: must be > 0 kg/m^3, got {self.density!r}")

    @property
    def lame(self) -> tuple[float, float]:
        """Lamé parameters (lambda, mu)."""
        e, nu = self.young, self.poisson
        return e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))
