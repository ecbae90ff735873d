"""A grasper held by a haptic device takes the liver's left lobe, pulls it against the stomach and ribs, and lets go."""

from dataclasses import dataclass, field

from scenes.liver_press import abdominal_contact, abdominal_liver, abdominal_solver, abdominal_stomach, ribs
from tissue.contact import Contact, Obstacle
from tissue.haptics.layer import Haptics, Tool
from tissue.scene import Render, Scene, Solver, SoftBody

# The device's path (t, x, y, z, jaw opening): from beside the left lobe's tip (as it hangs under
# gravity: 2.5-3 cm thick there), jaws 5 cm open above and below it, in along -x and a little down
# (the lower jaw clear of the stomach below), closed to 1.2 cm between the jaws' centres (4 mm
# between their faces) on the lobe, pulled 2.5 cm posterior and 2 cm down (the liver onto the
# stomach, the right lobe toward the ribs), held; released: the jaws opened to 4 cm while the
# device rises 1 cm (the lower jaw stays off the stomach), moved back to where the lobe's tip
# hangs, level with its middle, and out along +x. (Moved back 1 cm higher, the lower jaw's face
# came 1.8 cm under the middle of the released lobe, inside its underside: the contact
# correction folded elements there over, det F < 0.)
# The device eases in and out of each key, as a hand does: a linear path's velocity jumps at the
# keys (the pull's stop, the release) kicked the 5 g jaws into the lobe, 30-90 N on a few contact
# points for a step, with the same effect.
TIP = (0.038, -0.015, -0.012)
PULL = (0.0, 0.025, -0.02)
OPEN, CLOSED, RELEASED = 0.05, 0.012, 0.04


def _path() -> tuple[float, ...]:
    x, y, z = TIP
    px, py, pz = x + PULL[0], y + PULL[1], z + PULL[2]
    keys = [(0.0, x + 0.055, y, z + 0.01, OPEN), (0.6, x, y, z, OPEN), (1.2, x, y, z, CLOSED),
            (2.4, px, py, pz, CLOSED), (2.8, px, py, pz, CLOSED), (3.2, px, py, pz + 0.01, RELEASED),
            (3.6, x, y, z, RELEASED), (4.0, x + 0.055, y, z, RELEASED)]
    return tuple(v for key in keys for v in key)


@dataclass
class LiverGrasp(Scene):
    """The liver grasped by a haptic device's grasper, pulled against stomach and ribs, released.

    The liver and stomach of `liver_press` (co-rotational, E = 3 and 4 kPa, ν = 0.45), the same 20
    rib capsules. A grasper (two flat jaws, 2.4 cm long, 1.2 cm wide, 8 mm thick, closing along z:
    rounded bars 8 mm thick slipped between the contact points of the lobe's surface, its
    vertices, edge midpoints and face centroids, edges 1.7 cm long (median), and wedged them
    apart sideways until an element inverted)
    follows a scripted device through a virtual coupling (M 5 g, B 2 N·s/m, K 300 N/m; μ 0.8 on
    the jaws): it closes on the lobe's tip (to 4 mm between the jaws' faces), pulls it 3.2 cm
    toward the stomach, holds, opens and withdraws. The jaws' compliance h A_hap⁻¹ enters W as the
    paper's §3.6 says. The haptics stage writes forces.png: the force the device renders at the
    simulation's rate (held between 40 ms steps) and at 1 kHz (the haptic loop's re-solve of each
    step's problem for the device's pose between steps, each new step's correction blended in
    over a step), the grip, and what the contacts did (liver on stomach and ribs, the share of
    the jaws' contacts sliding), with the script's closing and opening shaded.
    """

    dt: float = 0.04
    duration: float = 4.0
    liver: SoftBody = field(default_factory=abdominal_liver)
    stomach: SoftBody = field(default_factory=abdominal_stomach)
    ribs: Obstacle = field(default_factory=ribs)
    grasper: Tool = field(default_factory=lambda: Tool(
        kind="grasper", keyframes=_path(), smooth=True, jaw_length=0.024, jaw_width=0.012, radius=0.004, mass=0.005,
        damping=2.0, stiffness=300.0, friction=0.8))
    contact: Contact = field(default_factory=abdominal_contact)
    haptics: Haptics = field(default_factory=Haptics)
    solver: Solver = field(default_factory=abdominal_solver)
    render: Render = field(default_factory=lambda: Render(
        every=2, figure=0.5, title="Liver grasped and pulled against the stomach and ribs"))
