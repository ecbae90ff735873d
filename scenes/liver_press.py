"""The liver pushed by a rigid probe against the ribs and the stomach (paper §3.7's contact scene)."""

import math
from dataclasses import dataclass, field

from tissue.contact import Contact, Obstacle
from tissue.scene import Fixed, Render, Scene, Solver, SoftBody

# The probe's path: from in front of the left lobe, 6 cm toward the stomach (posterior, left, a
# little down) in 2.4 s, then held.
PUSH = (0.562, 0.803, -0.2)
PROBE_RADIUS = 0.015
PROBE_START = (-0.0052, -0.0576, 0.0056)     # 3 mm in front of the lobe's anterior face
TRAVEL, PUSH_TIME = 0.06, 2.4


def rib_segments(centre=(-0.04, 0.0), arcs=((-0.015, 0.0952), (0.005, 0.0979), (0.025, 0.0955), (0.045, 0.0781)),
                 angles=(80.0, 220.0), pieces: int = 5) -> tuple[float, ...]:
    """Capsule axes (ax, ay, az, bx, by, bz, ...) of ribs: horizontal arcs around `centre` (x, y),
    one per (height z, radius), from `angles[0]` to `angles[1]` degrees (0 = +x, the patient's left;
    90 = +y, posterior), each cut into `pieces` straight segments. The defaults wrap the procedural
    liver's right lobe from behind (posterior) round to its right side, 2 mm clear of it."""
    out = []
    for z, r in arcs:
        a = [math.radians(angles[0] + (angles[1] - angles[0]) * k / pieces) for k in range(pieces + 1)]
        p = [(centre[0] + r * math.cos(t), centre[1] + r * math.sin(t), z) for t in a]
        for u, v in zip(p, p[1:]):
            out += [*u, *v]
    return tuple(round(c, 5) for c in out)


# The abdomen this scene and liver_grasp share: the liver hung from its upper fifth, the stomach
# held by its posterior part, the ribs, contact on face-sampled points with compliance warping.
def abdominal_liver() -> SoftBody:
    return SoftBody(mesh="liver", tets=1300, young=3000.0, poisson=0.45, density=300.0,
                    fixed=Fixed(region=(0.0, 1.0, 0.0, 1.0, 0.8, 1.0)))


def abdominal_stomach() -> SoftBody:
    return SoftBody(mesh="stomach", tets=800, young=4000.0, poisson=0.45, density=300.0,
                    fixed=Fixed(region=(0.0, 1.0, 0.45, 1.0, 0.0, 1.0)))


def ribs() -> Obstacle:
    return Obstacle(shape="capsules", radius=0.006, segments=rib_segments(), color="#e4d8bd")


def abdominal_contact() -> Contact:
    return Contact(friction=0.3, distance=3e-3, compliance="warped", tolerance=1e-6, max_iterations=100,
                   sampling="faces")


def abdominal_solver() -> Solver:
    """Each step solved to ‖r‖/‖b‖ ≤ 1e-3, by the cheapest setting of python -m bench.scene_defaults."""
    return Solver(cg_iterations=100, cg_tolerance=1e-3, preconditioner="multigrid", rayleigh_mass=0.1,
                  rayleigh_stiffness=0.05)


def _probe_path() -> tuple[float, ...]:
    n = math.sqrt(sum(c * c for c in PUSH))
    end = tuple(TRAVEL * c / n for c in PUSH)
    return (0.0, 0.0, 0.0, 0.0, PUSH_TIME, *end)


@dataclass
class LiverPress(Scene):
    """The liver (1,300 tetrahedra) pushed by a probe into the stomach and against the ribs.

    The liver hangs from its upper fifth (the diaphragm), the stomach is held by its posterior
    55 % (held by less, its free curve sags 5-10 cm under gravity); both are co-rotational soft
    bodies (E = 3 and 4 kPa, ν = 0.45, lowered density as in the `liver` scene). Ribs: 20 rigid
    capsules wrapping the right lobe from behind. A sphere (r 1.5 cm) pushes the left lobe 6 cm
    toward the stomach over 2.4 s, then holds. Contact with Coulomb friction (μ 0.3) on points
    sampled at the vertices, edge midpoints and centroids of the surfaces (so the probe cannot
    slip between vertices): 70-130 contacts, 200-400 constraint rows while pressed (10-23 of the
    contacts liver-stomach), solved with compliance warping as in the paper; dt 40 ms.
    """

    dt: float = 0.04
    duration: float = 3.2
    liver: SoftBody = field(default_factory=abdominal_liver)
    stomach: SoftBody = field(default_factory=abdominal_stomach)
    ribs: Obstacle = field(default_factory=ribs)
    probe: Obstacle = field(default_factory=lambda: Obstacle(
        shape="sphere", centre=PROBE_START, radius=PROBE_RADIUS, keyframes=_probe_path(), color="#7f8c9c"))
    contact: Contact = field(default_factory=abdominal_contact)
    solver: Solver = field(default_factory=abdominal_solver)
    # The figure at t = 1.6 s (4 cm into the push): beyond, the lobe's tip squeezed between probe
    # and stomach folds further than compliance warping represents (its elements turn apart), the
    # correction crushes its tetrahedra (inverted from 2.16 s: bench/press_inversion.py) and the
    # smooth surface drawn over them wrinkles.
    render: Render = field(default_factory=lambda: Render(
        every=2, figure=0.5, title="Liver pushed by a probe against the ribs and stomach"))
