"""The three procedural organs side by side, each hanging from a few holds near its top (no contact)."""

from dataclasses import dataclass, field

from tissue.scene import Fixed, Render, Scene, Solver, SoftBody


def _held_at_top(mesh: str, young: float, position, region=(0.2, 0.8, 0.25, 0.75, 0.9, 1.0)) -> SoftBody:
    """An organ of 1,300 tetrahedra held at three small patches spread over `region` (near its top)."""
    return SoftBody(mesh=mesh, tets=1300, young=young, poisson=0.3, density=300.0, position=position,
                    fixed=Fixed(region=region, count=3, radius=0.01))


@dataclass
class Organs(Scene):
    """Liver, stomach and colon side by side, each hanging from three holds, coloured by stress.

    The organs of `tissue.mesh.organs` seen from the front, moved apart along x (6 cm gaps: in
    their anatomical frame they sit too close to hang freely without contact) and aligned at the
    top. Three bodies, each with its own mesh, FEM and solver, stepped by the same free-motion
    stage; nothing touches, so no contact stage is built. Colours: von Mises stress, highest
    around the holds.
    """

    dt: float = 0.02
    duration: float = 2.0
    liver: SoftBody = field(default_factory=lambda: _held_at_top("liver", 3000.0, (-0.27, 0.0, -0.07)))
    stomach: SoftBody = field(default_factory=lambda: _held_at_top("stomach", 2000.0, (-0.086, 0.0, -0.023)))
    colon: SoftBody = field(default_factory=lambda: _held_at_top(
        "colon", 4000.0, (0.258, 0.0, 0.16), region=(0.0, 1.0, 0.0, 1.0, 0.75, 1.0)))
    # Each step solved to ‖r‖/‖b‖ ≤ 1e-3, by the cheapest setting of python -m bench.scene_defaults.
    solver: Solver = field(default_factory=lambda: Solver(
        cg_iterations=100, cg_tolerance=1e-3, preconditioner="multigrid", rayleigh_mass=0.1, rayleigh_stiffness=0.02))
    render: Render = field(default_factory=lambda: Render(
        every=3, scalars="von_mises", camera="front", ground=False, size=(1280, 720),
        animation_size=(640, 360), title="Liver, stomach and colon hanging from their holds"))
