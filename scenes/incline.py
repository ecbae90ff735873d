"""A soft block sliding down a tilted rigid plane: Coulomb friction, a = g (sin θ - μ cos θ)."""

import math
from dataclasses import dataclass, field

from tissue.contact import Contact, Obstacle
from tissue.scene import Render, Scene, Solver, SoftBody

ANGLE = 25.0        # degrees; tan 25° = 0.47 > μ = 0.4: the block slides at 0.59 m/s²
HALF_HEIGHT = 0.025


def _slope_normal(degrees: float) -> tuple[float, float, float]:
    a = math.radians(degrees)
    return (-math.sin(a), 0.0, math.cos(a))


@dataclass
class Incline(Scene):
    """A 10 × 10 × 5 cm block (E = 50 kPa) released on a plane tilted by 25°, μ = 0.4.

    tan 25° = 0.47 exceeds μ, so it slides down the slope with a = g (sin θ - μ cos θ) = 0.59 m/s²
    (tests/test_contact.py measures 0.5899, 0.06 % off); set `contact.friction=0.5` and it sticks.
    The plane passes through the origin; the block starts resting on it, its base 0.5 mm above.
    """

    dt: float = 0.01
    duration: float = 1.0
    block: SoftBody = field(default_factory=lambda: SoftBody(
        mesh="box", size=(0.1, 0.1, 2 * HALF_HEIGHT), cells=(4, 4, 2), young=5e4, poisson=0.3,
        density=1000.0, orientation=(0.0, -ANGLE, 0.0),
        position=tuple((HALF_HEIGHT + 5e-4) * n for n in _slope_normal(ANGLE))))
    slope: Obstacle = field(default_factory=lambda: Obstacle(shape="plane", normal=_slope_normal(ANGLE),
                                                             color="#d9d3c7"))
    contact: Contact = field(default_factory=lambda: Contact(friction=0.4, distance=2e-3, tolerance=1e-8,
                                                             max_iterations=200))
    # Each step solved to ‖r‖/‖b‖ ≤ 1e-3, by the cheapest setting of python -m bench.scene_defaults.
    solver: Solver = field(default_factory=lambda: Solver(cg_iterations=100, cg_tolerance=1e-3, preconditioner="multigrid",
                                                          rayleigh_mass=0.0, rayleigh_stiffness=0.01))
    # The block in a tissue colour over the faint start position (the distance slid shows; a
    # displacement colour map would paint the whole translating block one colour).
    render: Render = field(default_factory=lambda: Render(
        every=4, camera="iso", edges=True, ground=False, scalars=None, ghost=True,
        title="Block sliding on a 25° slope (μ = 0.4)"))
