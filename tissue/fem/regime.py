"""Where each rotation method's linear co-rotational element holds: a check before the first step.

Two dimensionless numbers of a body under gravity g, from its material (E, ν, ρ; Lamé λ, μ) and
the largest extent L of its rest shape:

  self-weight strain  s = ρ |g| L / E    the strain its own weight causes, at most (a column of
                                         height L on its base, a cantilever of length L at its clamp);
  spurious volume     (λ/μ) s            "large" only: its edge frame turns away from the polar
                                         rotation by an angle of the order of the shear strain γ ≈ s,
                                         so it reads a shear as a volume change of order γ², which λ
                                         stresses: λ γ² against the true shear stress μ γ.

"polar": the linear co-rotational energy stays finite when an element goes flat (its stress at zero
volume is of the order of E), so a load whose strain is of order one has minima with elements
inverted, whatever the integrator: refused above POLAR_STRAIN (a strain of one half). "large":
refused where its spurious volumetric stress outgrows the shear stress, (λ/μ) s > LARGE_VOLUME.
Both thresholds are "of order one" placed by the stability matrix (bench/stability.py,
docs/stability.md; the 0.1 m cantilever): "polar" fails every cell at s = 9.8 and 0.98 but
those with ν = 0 (and ν 0.3 at dt ≥ 0.04 s), and none at s ≤ 0.098; "large" fails no material
cell at (λ/μ) s ≤ 1.47 and every one at 4.8 and above where s ≥ 0.098 (at s = 0.0098 it is
bounded at 4.9). The cells these criteria refuse though they were bounded are counted there.
"invertible" (a compression barrier) and "linear" (small strain by its user's choice) are not
checked. The scenes (s ≤ 0.30, "polar") pass.
"""

import numpy as np

from ..errors import TissueError
from .material import Material

POLAR_STRAIN = 0.5      # the largest self-weight strain "polar" accepts
LARGE_VOLUME = 2.0      # the largest (λ/μ) s "large" accepts


def self_weight_strain(material: Material, gravity, extent: float) -> float:
    """ρ |g| L / E: the strain a body of extent L (m) takes under its own weight, at most."""
    return material.density * float(np.linalg.norm(gravity)) * extent / material.young


def check_regime(rotation: str, material: Material, gravity, points: np.ndarray) -> None:
    """Raise TissueError, naming the fields and what to use instead, where `rotation` is outside
    its element's regime for this material and gravity over the rest shape `points` (n, 3)."""
    if rotation not in ("polar", "large") or len(points) == 0:
        return
    extent = float(np.ptp(points, axis=0).max())
    s = self_weight_strain(material, gravity, extent)
    lam, mu = material.lame
    what = (f"young={material.young:g} Pa, poisson={material.poisson:g}, density={material.density:g} kg/m³ "
            f"under |gravity|={np.linalg.norm(gravity):.3g} m/s² over the body's {extent:.3g} m: "
            f"self-weight strain ρ|g|L/E = {s:.2g}")
    if rotation == "polar" and s > POLAR_STRAIN:
        raise TissueError(f"rotation: 'polar' is refused for {what} > {POLAR_STRAIN:g}; linear co-rotational "
                          "elements have inverted equilibria under loads of the order of E. Use "
                          "rotation='invertible' (a compression barrier), or a larger young / smaller density")
    if rotation == "large" and lam / mu * s > LARGE_VOLUME:
        instead = "polar" if s <= POLAR_STRAIN else "invertible"
        raise TissueError(f"rotation: 'large' is refused for {what}, λ/μ = {lam / mu:.3g}: (λ/μ)·s = "
                          f"{lam / mu * s:.2g} > {LARGE_VOLUME:g}, where its edge frames read shear as volume "
                          f"change and gain energy. Use rotation='{instead}', or a smaller poisson / larger young")
