"""Instruments: rigid tools held by a haptic device through a virtual coupling (paper §3.6).

Each jaw of an instrument is a rigid body (shapes in its own frame, a RigidObstacle for detection)
whose position follows a target set by the device (its pose and jaw opening) through a spring and
damper of stiffness K, damping B, on a mass M (the gains of the device's control loop). Over a
step of h, by implicit Euler like the soft bodies,

    M (v⁺ - v) = h K (x_d - x⁺) + h B (v_d - v⁺) + Hᵀ λ,     x⁺ = x + h v⁺,
    A v⁺ = M v + h K (x_d - x) + h B v_d + Hᵀ λ,              A = M + h B + h² K,

so the free motion is v_free = A⁻¹ (M v + h K (x_d - x) + h B v_d), x_free = x + h v_free, and the
contact impulses λ add x⁺ - x_free = h A⁻¹ Hᵀ λ: the jaw's compliance h A⁻¹ (scalar × I₃) enters W
like a soft body's (W += h Hⱼ Hⱼᵀ / A over the rows that touch the jaw, Hⱼ their jaw block: minus the
row direction, as a rigid point's motion enters the gap with the opposite sign). The jaw's
orientation is the device's (prescribed: the coupling acts on translation only), so a contact's
lever arm adds no compliance. The force the device renders is the spring's, K (x - x_d): at rest it
balances the contact force on the jaw.

A jaw takes part in the contact stage (tissue.contact.ContactStage, `instruments=`) as one more
"body" of one node: `prepare`, `add_to`, `factor_size`, `factor`, `correct` are the compliance
interface the stage calls on its soft bodies' WarpedCompliance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..contact.obstacles import RigidObstacle
from ..errors import TissueError


@dataclass(frozen=True)
class Coupling:
    """The virtual coupling's gains: mass (kg), damping (N·s/m), stiffness (N/m)."""

    mass: float = 0.02
    damping: float = 2.0
    stiffness: float = 300.0

    def __post_init__(self):
        for name in ("mass", "damping", "stiffness"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise TissueError(f"coupling.{name}: must be a finite number >= 0, got {value!r}")
        if self.mass <= 0:
            raise TissueError(f"coupling.mass: must be > 0 kg, got {self.mass!r}")

    def matrix(self, h: float) -> float:
        """A = M + h B + h² K (a scalar: the same on every axis)."""
        return self.mass + h * self.damping + h * h * self.stiffness

    def follow(self, h: float) -> float:
        """∂x_free / ∂x_d = (h² K + h B) / A: how much of a target's move within a step the jaw's
        free motion makes (its velocity taken as the move over h)."""
        return (h * h * self.stiffness + h * self.damping) / self.matrix(h)


@dataclass
class DevicePose:
    """What a device reports: tip position (m), orientation (3×3, columns the tool's axes in the
    world), jaw opening (m; 0 for a probe), and the device's clock (s)."""

    position: np.ndarray
    orientation: np.ndarray
    jaw: float = 0.0
    time: float = 0.0

    @staticmethod
    def at(position, jaw: float = 0.0, time: float = 0.0, orientation=None) -> "DevicePose":
        R = np.eye(3) if orientation is None else np.asarray(orientation, dtype=np.float64).reshape(3, 3)
        return DevicePose(np.asarray(position, dtype=np.float64).reshape(3), R, float(jaw), float(time))


class Jaw:
    """One rigid part of an instrument, coupled to its target (see the module docstring)."""

    def __init__(self, shapes, coupling: Coupling, offset=(0.0, 0.0, 0.0), opening_axis=(0.0, 0.0, 0.0),
                 friction: float | None = None, name: str = "jaw"):
        self.coupling, self.name = coupling, name
        self.offset = np.asarray(offset, dtype=np.float64)          # target = p + R (offset + jaw/2 · axis)
        self.opening_axis = np.asarray(opening_axis, dtype=np.float64)
        self.obstacle = RigidObstacle(shapes, motion=self._pose, friction=friction, name=name)
        self.x = self.x_start = self.target = np.zeros(3)
        self.v = np.zeros(3)
        self.R = self.R_start = np.eye(3)
        self.end_time, self.h = 0.0, 1.0
        self.jds = None

    # ---- state -----------------------------------------------------------------------------------

    def target_of(self, pose: DevicePose) -> np.ndarray:
        return pose.position + pose.orientation @ (self.offset + 0.5 * pose.jaw * self.opening_axis)

    def place(self, pose: DevicePose) -> None:
        """Put the jaw at rest on its target (the start of a run)."""
        self.x = self.x_start = self.target = self.target_of(pose)
        self.v = np.zeros(3)
        self.R = self.R_start = pose.orientation

    def free_motion(self, pose: DevicePose, previous: DevicePose, h: float, end_time: float) -> None:
        """The step's free motion toward the target of `pose` (the target's velocity: its move
        since `previous`, over h)."""
        c = self.coupling
        target = self.target_of(pose)
        target_velocity = (target - self.target_of(previous)) / h
        self.x_start, self.R_start = self.x, self.R
        v_free = (c.mass * self.v + h * c.stiffness * (target - self.x) + h * c.damping * target_velocity) / c.matrix(h)
        self.v, self.x = v_free, self.x + h * v_free
        self.target, self.R, self.h, self.end_time = target, pose.orientation, h, end_time
        self.jds = None                                  # no rows yet this step

    def coupling_force(self) -> np.ndarray:
        """The spring's force on the device, K (x - x_d) (N)."""
        return self.coupling.stiffness * (self.x - self.target)

    def _pose(self, time: float):
        """The pose detection asks for: the step's start, or its end (the current state)."""
        if time < self.end_time - 0.5 * self.h:
            return self.R_start, self.x_start
        return self.R, self.x

    # ---- the compliance interface of the contact stage -------------------------------------------

    free = False

    def compliance(self) -> float:
        """h A⁻¹ (m per N·s), the jaw's compliance on every axis."""
        return self.h / self.coupling.matrix(self.h)

    def factorise(self) -> None:
        """(The exact-compliance path asks for it; a jaw's compliance is already exact.)"""

    def prepare(self, jds, body: int | None = None) -> None:
        """The rows' blocks on the jaw: a JaggedDiagonal, or ConstraintRows and the jaw's body id."""
        if body is not None:
            from ..contact.constraints import JaggedDiagonal
            jds = JaggedDiagonal(jds, body)
        self.jds = jds

    def factor_size(self, jds) -> int:
        return 3

    def _blocks(self):
        """(block rows, their 3×3 blocks on the jaw), one block per row (a contact touches one jaw once)."""
        if self.jds is None:
            return np.zeros(0, np.int64), np.zeros((0, 3, 3))
        return self.jds.row, self.jds.value.astype(np.float64)

    def add_to(self, W: np.ndarray) -> None:
        """W += h A⁻¹ Hⱼ Hⱼᵀ among the rows that touch the jaw."""
        rows, V = self._blocks()
        if not len(rows):
            return
        G = V.reshape(-1, 3)                                   # (3 rows per block) × 3
        index = (3 * rows[:, None] + np.arange(3)).ravel()
        W[np.ix_(index, index)] += self.compliance() * (G @ G.T)

    def factor(self, P: np.ndarray, Q: np.ndarray, diagonal: np.ndarray, pos: np.ndarray, q_offset: int = 0,
               pos_offset: int = 0) -> None:
        """The jaw's factors of W (FactoredDelassus, scale h): its blocks of P (at
        pos[pos_offset:]), Q = A⁻¹ I₃ (from q_offset), and its part of W's diagonal blocks."""
        rows, V = self._blocks()
        if not len(rows):
            return
        inverse = 1.0 / self.coupling.matrix(self.h)
        P[pos[pos_offset:pos_offset + len(rows)]] = V
        Q[q_offset:q_offset + 9] = (inverse * np.eye(3)).ravel()
        np.add.at(diagonal, rows, self.compliance() * np.einsum("eab,ecb->eac", V, V))

    def correct(self, lam: np.ndarray) -> None:
        """x += h A⁻¹ Hⱼᵀ λ, v += that / h."""
        impulse = self.impulse(lam)
        dx = self.compliance() * impulse
        self.x = self.x + dx
        self.v = self.v + dx / self.h

    def impulse(self, lam: np.ndarray) -> np.ndarray:
        """Hⱼᵀ λ: the contacts' total impulse on the jaw (N·s)."""
        rows, V = self._blocks()
        if not len(rows):
            return np.zeros(3)
        L = np.asarray(lam, dtype=np.float64)[(3 * rows[:, None] + np.arange(3))]
        return np.einsum("eab,ea->b", V, L)


class Instrument:
    """Jaws moved together by one device: a probe (one jaw) or a grasper (two, opening apart).

    device: time -> DevicePose, read by the contact stage at the end of each step (a Trajectory, a
    HapticLoop's `device_pose`); color: how the run's images draw it (None: obstacle grey)."""

    def __init__(self, jaws: list[Jaw], name: str = "instrument", device=None, color: str | None = None):
        if not jaws:
            raise TissueError(f"{name}: an instrument needs at least one jaw")
        self.jaws, self.name, self.device, self.color = list(jaws), name, device, color
        self.pose = self.previous = None

    def place(self, pose: DevicePose) -> None:
        for jaw in self.jaws:
            jaw.place(pose)
        self.pose = self.previous = pose

    def free_motion(self, pose: DevicePose, h: float, end_time: float) -> None:
        if not isinstance(pose, DevicePose):
            raise TissueError(f"{self.name}: its device gave {type(pose).__name__}, expected a DevicePose")
        if self.pose is None:
            self.place(pose)
        self.previous, self.pose = self.pose, pose
        for jaw in self.jaws:
            jaw.free_motion(pose, self.previous, h, end_time)

    def coupling_force(self) -> np.ndarray:
        """The force the device renders: the jaws' springs summed (N)."""
        return sum(j.coupling_force() for j in self.jaws)

    def grip_force(self) -> float:
        """The squeeze on the jaws along their opening (N; > 0: something between them resists
        closing): half the difference of their springs' forces along their opening axes."""
        if self.pose is None:
            return 0.0
        R = self.pose.orientation
        return 0.5 * sum(float(j.coupling_force() @ (R @ j.opening_axis)) for j in self.jaws)


def probe(shapes, coupling: Coupling, friction: float | None = None, name: str = "probe") -> Instrument:
    """One jaw at the device's tip."""
    return Instrument([Jaw(shapes, coupling, friction=friction, name=name)], name)


def grasper(jaw_shapes, coupling: Coupling, axis=(0.0, 1.0, 0.0), friction: float | None = None,
            name: str = "grasper") -> Instrument:
    """Two jaws, each made of `jaw_shapes` in its own frame, at ± half the opening along `axis`
    (the device frame) from the tip; the jaws' inner faces are where their shapes face each other."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return Instrument([Jaw(jaw_shapes, coupling, opening_axis=axis, friction=friction, name=f"{name}.upper"),
                       Jaw(jaw_shapes, coupling, opening_axis=-axis, friction=friction, name=f"{name}.lower")], name)
