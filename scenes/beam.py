"""A cantilever beam clamped at x = 0 sagging under its own weight: the classic co-rotational figure."""

from dataclasses import dataclass, field

from tissue.scene import Fixed, Render, Scene, Solver, SoftBody


@dataclass
class Beam(Scene):
    """A cantilever beam clamped at one end, sagging under gravity and settling.

    1 m × 0.1 m × 0.1 m, E = 2 MPa, ν = 0.3, 1000 kg/m³, clamped on its x = 0 face: the tip drops
    by about a third of the length, a rotation large enough that a linear (non-rotated) model would
    visibly stretch the beam, while the co-rotational one keeps its length. The rest shape is
    drawn faintly behind it.
    """

    dt: float = 0.01
    duration: float = 2.0
    beam: SoftBody = field(default_factory=lambda: SoftBody(
        mesh="beam", size=(1.0, 0.1, 0.1), cells=(20, 2, 2),
        young=2e6, poisson=0.3, density=1000.0, fixed=Fixed.end("-x")))
    # Each step solved to ‖r‖/‖b‖ ≤ 1e-3, by the cheapest setting of python -m bench.scene_defaults.
    solver: Solver = field(default_factory=lambda: Solver(cg_iterations=100, cg_tolerance=1e-3,
                                                          preconditioner="multigrid"))
    render: Render = field(default_factory=lambda: Render(
        every=4, camera="front", edges=True, ghost=True, ground=False,
        title="Cantilever beam under gravity (E = 2 MPa)"))
