"""The contact layer as a scene declares it: the `Contact` (the stage's settings, from
tissue.contact.pipeline) and `Obstacle` option groups, and the stage the Simulation runs right
after the free motion (registered on import).

    @dataclass
    class Press(Scene):
        liver: SoftBody = ...
        floor: Obstacle = field(default_factory=lambda: Obstacle(shape="plane", centre=(0, 0, -0.05)))
        probe: Obstacle = field(default_factory=lambda: Obstacle(
            shape="sphere", radius=0.01, keyframes=(0, 0, 0, 0, 1, 0, 0, -0.02)))
        contact: Contact = field(default_factory=lambda: Contact(friction=0.3))

Every soft body of the scene takes part; every `Obstacle` field is a rigid obstacle, named by its
field. A scene with obstacles must declare a `Contact` (the settings live there, and a scene
without contact builds nothing of this layer).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import TissueError
from ..options import Options, require
from ..body import rotation_matrix
from ..simulation import Drawable, add_stage
from .obstacles import Box, Capsule, Plane, RigidObstacle, Sphere, TriangleMesh, plane_axes, shape_surface
from .pipeline import Contact, ContactBody, ContactStage


@dataclass
class Obstacle(Options):
    """A rigid obstacle of one kind of shape (tissue.contact.obstacles), in the world frame.

    plane     through `centre`, outward `normal` (the solid is below it)
    sphere    `centre`, `radius`
    capsules  `segments` = (ax, ay, az, bx, by, bz) per capsule, all of `radius` (ribs)
    box       `centre`, half-extents `half`, turned by `orientation`
    mesh      the closed surface file `path`, turned by `orientation` then moved by `centre`
    Motion: `keyframes` = (t, dx, dy, dz) per key, a translation interpolated linearly in time and
    held before the first key and after the last (none: the obstacle stays put).
    friction: its own Coulomb coefficient (None: the Contact's). color: how the run's images draw
    it (a plane as a patch around the bodies).
    """

    shape: Literal["plane", "sphere", "capsules", "box", "mesh"] = "plane"
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius: float = 0.01
    half: tuple[float, float, float] = (0.05, 0.05, 0.05)
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    segments: tuple[float, ...] = ()
    path: str = ""
    keyframes: tuple[float, ...] = ()
    friction: float | None = None
    color: str = ""                 # in the run's images; "" for the renderer's obstacle grey

    def check(self):
        require(self.radius > 0, "radius", f"must be > 0 m, got {self.radius}")
        require(all(h > 0 for h in self.half), "half", f"half-extents must be > 0 m, got {self.half}")
        require(any(self.normal), "normal", "must be non-zero")
        require(len(self.segments) % 6 == 0, "segments",
                f"expected 6 numbers (a, b) per capsule, got {len(self.segments)}")
        require(self.shape != "capsules" or self.segments, "segments", "a 'capsules' obstacle needs segments")
        require(self.shape != "mesh" or self.path, "path", "a 'mesh' obstacle needs a surface file")
        require(len(self.keyframes) % 4 == 0, "keyframes",
                f"expected 4 numbers (t, dx, dy, dz) per key, got {len(self.keyframes)}")
        times = self.keyframes[::4]
        require(all(b > a for a, b in zip(times, times[1:])), "keyframes", f"times must increase, got {times}")
        require(self.friction is None or self.friction >= 0, "friction", f"must be >= 0, got {self.friction}")

    def shapes(self) -> list:
        R = rotation_matrix(self.orientation)
        if self.shape == "plane":
            return [Plane(self.centre, self.normal)]
        if self.shape == "sphere":
            return [Sphere(self.centre, self.radius)]
        if self.shape == "capsules":
            s = np.asarray(self.segments, dtype=np.float64).reshape(-1, 6)
            return [Capsule(tuple(a), tuple(b), self.radius) for a, b in zip(s[:, :3], s[:, 3:])]
        if self.shape == "box":
            return [Box(self.centre, self.half, R)]
        from ..mesh.closed_surface import read_surface

        points, triangles = read_surface(self.path)
        return [TriangleMesh(points @ R.T + self.centre, triangles)]

    def motion(self):
        """time -> translation, or None for a static obstacle."""
        if not self.keyframes:
            return None
        # Each column contiguous: np.interp copies a strided one at every call.
        times, *axes = np.asarray(self.keyframes, dtype=np.float64).reshape(-1, 4).T.copy()
        return lambda t: np.array([np.interp(t, times, axis) for axis in axes])

    def build(self, name: str) -> RigidObstacle:
        try:
            return RigidObstacle(self.shapes(), motion=self.motion(), friction=self.friction, name=name)
        except TissueError as err:
            raise TissueError(f"{name}: {err}") from None


class ContactLayer:
    """Steps 2-5 of the data flow (detection, constraints, compliance, LCP, correction)."""

    name = "contact"

    def __init__(self, sim, settings: Contact, obstacles: dict[str, Obstacle]):
        self.specs = obstacles
        self.obstacles = {name: spec.build(name) for name, spec in obstacles.items()}
        bodies = [ContactBody(b.solver, b.faces) for b in sim.bodies.values()]
        # Instruments: the scene's parts that build one (tissue.haptics.Tool), coupled to a device.
        self.instruments = {name: spec.build_instrument(name) for name, spec in sim.scene.parts(Options).items()
                            if hasattr(spec, "build_instrument")}
        self.stage = ContactStage(bodies, list(self.obstacles.values()), settings,
                                  instruments=list(self.instruments.values()))

    def step(self, sim) -> None:
        result = self.stage.step(time=sim.time + sim.dt)
        c = result.contacts
        # Soft–soft contacts and jaws (bodies of one node, moved by the correction too) trade
        # energy that the obstacles' work cannot count: the bodies they touch keep the budget of
        # their free motion.
        soft = c.soft.nonzero()[0]
        jawed = self.stage.on_jaws(c).nonzero()[0]
        trading = set(c.body[soft].tolist()) | set(c.other[soft].tolist()) | set(c.body[jawed].tolist())
        for i, body in enumerate(sim.bodies.values()):     # the step ends after the correction
            budget = getattr(body.stepper, "budget", None)
            if budget is not None and len(c) and i not in trading:
                close_budget(budget, result, i, self.stage.settings.tolerance)

    def report(self) -> tuple[dict[str, float], dict[str, float]]:
        """Seconds of the last step by sub-stage, and the counters (contacts, rows, GS iterations
        and residual, penetration)."""
        stats = self.stage.stats
        return {k: v[-1] for k, v in stats.times.items() if v}, dict(stats.counters)

    def drawables(self) -> list[Drawable]:
        """The obstacles, for the run's images (see tissue.simulation.Drawable)."""
        out = []
        for name, obstacle in self.obstacles.items():
            planes = any(isinstance(s, Plane) for s in obstacle.shapes)
            out.append(Drawable(
                name=name, surface=lambda bounds, o=obstacle: obstacle_surface(o, bounds),
                pose=lambda time, n=name: self.obstacle_transform(n, time), moving=obstacle.motion is not None,
                framed=not planes, flat=planes, color=self.specs[name].color or None))
        return out

    def obstacle_transform(self, name: str, time: float) -> np.ndarray:
        """4×4 pose of an obstacle at `time` (for drawing its `surface()`)."""
        R, t = self.obstacles[name].pose(time)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return T


def close_budget(budget, result, body: int, tolerance: float) -> None:
    """Close the energy budget (tissue.solver.energy_budget) of soft body `body` after the
    correction of `result`: with the obstacles' work, the contact reactions' allowance and the
    correction's impulses."""
    budget.add_work(obstacle_work(result, body))
    budget.add_allowance(contact_allowance(result, body, tolerance))
    budget.add_correction(correction_impulses(result, body, budget.solver.model.n_nodes))
    budget.close()


def obstacle_work(result, body: int) -> float:
    """The work (J) the obstacles did on `body` in the step of `result`: each of its contacts'
    force along the motion of the obstacle's touched point over the step (static obstacles do
    none; sliding friction's work relative to the obstacle is the body's loss, not the
    obstacle's). Soft–soft and jaw contacts trade energy between bodies, not counted: a body that
    had any keeps the budget of its free motion (tissue.solver.energy_budget)."""
    forces = result.contact_forces
    mine = result.contacts.body[:len(forces)] == body
    return float(np.einsum("kj,kj->", forces[mine], result.contacts.other_motion[:len(forces)][mine]))


def contact_allowance(result, body: int, tolerance: float) -> float:
    """A bound (J) on the energy the contact reactions on `body` may have added in the step of
    `result` beyond exact ones (tissue.solver.energy_budget): each reaction's force |λᵢ| / h over
    the constraint's violation, at most `tolerance` (m, or the solve's residual where it ended
    above it) at the step's end and at its start (the last solve's), 2 tolerance Σ |λᵢ| / h."""
    impulses = result.contact_impulses
    mine = result.contacts.body[:len(impulses)] == body
    violation = max(tolerance, result.info.residual if result.info is not None else 0.0)
    return 2.0 * violation * float(np.linalg.norm(impulses[mine], axis=1).sum()) / result.dt


def correction_impulses(result, body: int, n_nodes: int) -> np.ndarray:
    """Hᵀλ (n_nodes, 3, N·s): the impulses the reactions of `result` (contacts and attachments)
    apply at the nodes of `body`, which its correction moved it by."""
    out = np.zeros((n_nodes, 3))
    rows = result.rows
    if rows is None:
        return out
    mine = np.flatnonzero(rows.body == body)
    blocks = result.impulses.reshape(-1, 3)[rows.block[mine]]
    np.add.at(out, rows.node[mine], np.einsum("eij,ei->ej", rows.value[mine], blocks))
    return out


def obstacle_surface(obstacle: RigidObstacle, bounds) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of an obstacle in its own frame for drawing: curved shapes finely
    tessellated, a plane as a rectangle around the bodies' `bounds` seen along its normal (with a
    margin of a quarter of their extent on each side)."""
    b = np.asarray(bounds, dtype=np.float64).reshape(3, 2)
    corners = np.array(np.meshgrid(*b, indexing="ij")).reshape(3, -1).T
    points, triangles, offset = [], [], 0
    for shape in obstacle.shapes:
        if isinstance(shape, Plane):
            u, w = plane_axes(shape)
            origin = np.asarray(shape.point, dtype=np.float64)
            cu, cw = (corners - origin) @ u, (corners - origin) @ w
            margin = 0.25 * max(np.ptp(cu), np.ptp(cw), 1e-3)
            (u0, u1), (w0, w1) = (cu.min() - margin, cu.max() + margin), (cw.min() - margin, cw.max() + margin)
            p = origin + np.array([[u0, w0], [u1, w0], [u1, w1], [u0, w1]]) @ np.stack([u, w])
            t = np.array([[0, 1, 2], [0, 2, 3]])
        else:
            p, t = shape_surface(shape, resolution=32)
        points.append(p)
        triangles.append(np.asarray(t) + offset)
        offset += len(p)
    return np.concatenate(points), np.concatenate(triangles).astype(np.int64)


def contact(sim) -> ContactLayer | None:
    """The stage builder: a ContactLayer when the scene declares contact (None otherwise)."""
    declared = sim.scene.parts(Contact)
    obstacles = sim.scene.parts(Obstacle)
    if not declared:
        if obstacles:
            raise TissueError(f"{next(iter(obstacles))}: an obstacle needs contact; declare a field of type "
                              "Contact (tissue.contact.Contact) in the scene")
        return None
    if len(declared) > 1:
        raise TissueError(f"{', '.join(declared)}: a scene declares at most one Contact")
    return ContactLayer(sim, next(iter(declared.values())), obstacles)


add_stage(contact, after="free_motion")
