"""Cutting as a scene layer: a blade following a predefined path cuts a soft body over many steps.

A scene declares it with a field of type `Cut` (`cut: Cut = field(default_factory=lambda:
Cut(...))`); importing this module registers the stage, at the end of a step. Each step the blade
advances `speed × dt` along its path and the `Cutter` cuts what the swept surface has crossed; the
body (its rest mesh, boundary, held nodes, the faces on the cut) follows for the run's output, the
body's compliance A₀⁻¹ (a CuttingCompliance, when `compliance` is on) is updated, and a contact
stage, if the scene has one, reads its compliance from it. The blade is drawn in the run's images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import TissueError
from ..options import Options, require
from ..simulation import Drawable, add_stage
from .cutter import Cutter
from .surface import CutPath


@dataclass
class Cut(Options):
    """A predefined cut through a soft body.

    body: the soft body's field name ("" = the scene's first body). path: the points (x0, y0, z0,
    x1, y1, z1, ...) the blade's top end follows, in fractions of the body's posed bounding box
    (0 = its minimum, 1 = its maximum along each axis, as in `Fixed.region`; beyond 0-1 is outside
    the body). direction: the blade's direction from its top end; depth: its length (m). The blade
    enters the path at time `start` (s) and moves along it at `speed` (m/s). compliance: keep the
    body's compliance A₀⁻¹ exact through the cut (tissue.cutting.CuttingCompliance), with lazy
    low-rank factors folded when their rank passes `fold_rank` (0: eager, folded every step).
    """

    body: str = ""
    path: tuple[float, ...] = (0.5, -0.1, 1.1, 0.5, 1.1, 1.1)
    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    depth: float = 0.1
    start: float = 0.0
    speed: float = 0.05
    compliance: bool = True
    fold_rank: int = 240

    def check(self):
        require(len(self.path) >= 6 and len(self.path) % 3 == 0, "path",
                f"expected at least two points (x, y, z, x, y, z, ...), got {len(self.path)} values")
        require(any(d != 0 for d in self.direction), "direction", "must not be zero")
        require(self.depth > 0, "depth", f"must be > 0 m, got {self.depth}")
        require(self.start >= 0, "start", f"must be >= 0 s, got {self.start}")
        require(self.speed > 0, "speed", f"must be > 0 m/s, got {self.speed}")
        require(self.fold_rank >= 0, "fold_rank", f"must be >= 0, got {self.fold_rank}")


class _BodyCut:
    """One Cut acting on its body."""

    def __init__(self, sim, field: str, spec: Cut):
        from .compliance import CuttingCompliance

        names = list(sim.bodies)
        name = spec.body or names[0]
        if name not in sim.bodies:
            raise TissueError(f"{field}.body: no soft body named {name!r}; the scene has {', '.join(names)}")
        self.name, self.index, self.spec = name, names.index(name), spec
        self.body = body = sim.bodies[name]
        lo, hi = body.mesh.bounds()
        self.path = CutPath(lo + np.asarray(spec.path, np.float64).reshape(-1, 3) * (hi - lo), spec.direction,
                            spec.depth)
        solver = body.solver
        # Room for the cut's new nodes and elements before the compliance sizes C by the capacity.
        solver.model.reserve(nodes=solver.model.n_nodes // 4, elements=solver.model.n_elements // 4,
                             slots=solver.model.incidence_rows.shape[1] + 8)
        self.compliance = CuttingCompliance(solver.model, solver.dt, solver.rayleigh_mass, solver.rayleigh_stiffness,
                                            fold_rank=spec.fold_rank) if spec.compliance else None
        self.cutter = Cutter(solver.model, solver, self.compliance)

    def travelled(self, time: float) -> float:
        return float(np.clip(self.spec.speed * (time - self.spec.start), 0.0, self.path.length))

    def step(self, time: float, dt: float):
        """Cut what the blade sweeps from `time` to `time + dt`; the report, or None."""
        s0, s1 = self.travelled(time), self.travelled(time + dt)
        if s1 <= s0:
            return None
        report = self.cutter.cut(self.path.sweep(s0, s1))
        if report.nodes_added or report.split:
            self.body.follow_model(self.cutter.cut_faces())
        return report

    def blade(self) -> Drawable:
        """The blade, a thin plate 1 cm along the path, moved along it."""
        a, b = self.path.blade(0.0)
        along = self.path.points[1] - self.path.points[0]
        along = 0.005 * along / np.linalg.norm(along)
        points = np.array([a - along, a + along, b + along, b - along])

        def pose(time: float) -> np.ndarray:
            T = np.eye(4)
            T[:3, 3] = self.path.blade(self.travelled(time))[0] - a
            return T

        return Drawable(name=f"blade ({self.name})", surface=lambda bounds: (points, np.array([[0, 1, 2], [0, 2, 3]])),
                        pose=pose, moving=True, framed=False, color="#5d6570")


class CuttingLayer:
    """The cutting stage: every declared Cut advances its blade and cuts, once per step."""

    name = "cutting"

    def __init__(self, sim, cuts: dict[str, Cut]):
        self.cuts = [_BodyCut(sim, field, spec) for field, spec in cuts.items()]
        self._linked = False
        self.last = []

    def step(self, sim) -> None:
        if not self._linked:            # a contact stage reads the compliance we keep
            for stage in sim.stages:
                contact = getattr(stage, "stage", None)
                for cut in self.cuts:
                    if cut.compliance is not None and hasattr(contact, "follow_compliance"):
                        contact.follow_compliance(cut.index, cut.compliance)
            self._linked = True
        self.last = [r for r in (cut.step(sim.time, sim.dt) for cut in self.cuts) if r is not None]

    def report(self) -> tuple[dict[str, float], dict[str, float]]:
        """Seconds of the last step by sub-stage (geometry, model, state, compliance) and counters
        (elements split and created, nodes added; the worst quality of the elements created)."""
        seconds: dict[str, float] = {}
        counters = dict(cut_split=0, cut_created=0, cut_nodes_added=0)
        for r in self.last:
            for k, v in r.seconds.items():
                seconds[k] = seconds.get(k, 0.0) + v
            counters["cut_split"] += r.split
            counters["cut_created"] += r.created
            counters["cut_nodes_added"] += r.nodes_added
        created = [r for cut in self.cuts for r in cut.cutter.reports if r.created]
        if created:
            counters["cut_worst_dihedral"] = min(r.min_dihedral for r in created)
            counters["cut_worst_condition"] = max(r.max_condition for r in created)
        return seconds, counters

    def drawables(self) -> list[Drawable]:
        return [cut.blade() for cut in self.cuts]


def cutting(sim) -> CuttingLayer | None:
    """The stage builder: a CuttingLayer when the scene declares a Cut (None otherwise)."""
    cuts = sim.scene.parts(Cut)
    return CuttingLayer(sim, cuts) if cuts else None


add_stage(cutting)
