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

With contact (`check_contact_motion`, run when a contact stage is built), a third number, for any
rotation: the farthest a node's initial velocity carries it in one step, |v| dt, against the
body's thickness T (the smallest extent of its rest shape). Contact is corrected at the end of a
step, from the free motion's positions; a free motion that crosses more than the body's thickness
has the correction push nodes back through the body. Measured on the 10 m/s impact of the 2 cm
cantilever onto a floor at dt 0.04 s (|v| dt / T = 20): the first step's correction, with the
rest compliance, leaves 101 elements inverted and raises the elastic energy from 1.13 to 5.02 J
("invertible"); the cell gains energy or ends inverted with every rotation. Refused above one
thickness per step.
"""

import numpy as np

from ..errors import TissueError
from .material import Material

POLAR_STRAIN = 0.5      # the largest self-weight strain "polar" accepts
LARGE_VOLUME = 2.0      # the largest (λ/μ) s "large" accepts
CONTACT_TRAVEL = 1.0    # the most thicknesses a node's initial velocity may carry it in a contact step


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


def check_contact_motion(points: np.ndarray, velocities: np.ndarray, dt: float, body: str = "body") -> None:
    """Raise TissueError, naming dt and the velocities, where a node's velocity `velocities` (n, 3)
    carries it farther in one step than the thickness of the rest shape `points` (n, 3)."""
    if len(points) == 0:
        return
    thickness = float(np.ptp(points, axis=0).min())
    speeds = np.linalg.norm(velocities, axis=1)
    travel = float(speeds.max()) * dt
    if travel > CONTACT_TRAVEL * thickness:
        node = int(np.argmax(speeds))
        raise TissueError(f"dt, velocities: {body}'s node {node} moves {travel:.3g} m in one step (|v| = "
                          f"{speeds[node]:.3g} m/s, dt = {dt:g} s), {travel / thickness:.3g} times the body's "
                          f"thickness {thickness:.3g} m; contact is corrected at the end of a step and cannot "
                          f"undo a free motion through the body. Use dt ≤ {CONTACT_TRAVEL * thickness / speeds[node]:.2g} s "
                          "(or a smaller initial velocity)")
