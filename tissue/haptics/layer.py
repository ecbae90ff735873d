"""Haptics as a scene declares it: a `Tool` (an instrument held by a scripted device, which the
contact stage couples in) and `Haptics` (the stage that logs the forces the device would render,
at the simulation's rate and at the haptic rate, and plots them beside the run's images).

    @dataclass
    class Grasp(Scene):
        liver: SoftBody = ...
        grasper: Tool = field(default_factory=lambda: Tool(kind="grasper", keyframes=(...)))
        contact: Contact = field(default_factory=Contact)
        haptics: Haptics = field(default_factory=Haptics)

In a `tissue run`, the haptic-rate forces are computed in the simulation's process, at the
device's poses between two steps (the same re-solve the haptic loop's process runs: deterministic,
whatever the machine's load); the real-time loop in its own process is tissue.haptics.loop's
HapticLoop (bench/haptics.py drives it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..contact.layer import obstacle_surface     # (also registers the contact stage, which this one follows)
from ..errors import TissueError
from ..options import Options, require
from ..scene import Drawable, add_stage, rotation_matrix
from .device import Trajectory
from .instrument import Coupling, Instrument, grasper, probe
from .lcp import MAX_CONTACTS, MAX_SWEEPS, HapticSolver, restrict


@dataclass
class Tool(Options):
    """An instrument held by a scripted device (tissue.haptics.instrument).

    kind: 'grasper' (two jaws `jaw` apart along the tool's z, each a rounded bar: a capsule of
    `radius` and `jaw_length` along the tool's x) or 'probe' (a sphere of `radius`).
    keyframes: (t, x, y, z, jaw opening) per key, the device's path, interpolated linearly;
    orientation: the tool's axes (degrees about x, y, z). mass (kg), damping (N·s/m), stiffness
    (N/m): the virtual coupling. friction: Coulomb μ of contacts on the jaws (None: the Contact's).
    """

    kind: Literal["grasper", "probe"] = "grasper"
    keyframes: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.02)
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    jaw_length: float = 0.024
    radius: float = 0.004
    mass: float = 0.02
    damping: float = 2.0
    stiffness: float = 300.0
    friction: float | None = None
    color: str = "#7f8c9c"

    def check(self):
        require(len(self.keyframes) % 5 == 0 and self.keyframes, "keyframes",
                f"expected 5 numbers (t, x, y, z, jaw) per key, got {len(self.keyframes)}")
        times = self.keyframes[::5]
        require(all(b > a for a, b in zip(times, times[1:])), "keyframes", f"times must increase, got {times}")
        require(all(j >= 0 for j in self.keyframes[4::5]), "keyframes", "jaw openings must be >= 0")
        require(self.jaw_length > 0, "jaw_length", f"must be > 0 m, got {self.jaw_length}")
        require(self.radius > 0, "radius", f"must be > 0 m, got {self.radius}")
        require(self.mass > 0, "mass", f"must be > 0 kg, got {self.mass}")
        require(self.damping >= 0, "damping", f"must be >= 0, got {self.damping}")
        require(self.stiffness >= 0, "stiffness", f"must be >= 0, got {self.stiffness}")
        require(self.friction is None or self.friction >= 0, "friction", f"must be >= 0, got {self.friction}")

    def trajectory(self) -> Trajectory:
        return Trajectory(np.asarray(self.keyframes, dtype=np.float64).reshape(-1, 5),
                          orientation=rotation_matrix(self.orientation))

    def build_instrument(self, name: str) -> Instrument:
        """The instrument, its device the scripted trajectory (the contact layer calls this)."""
        from ..contact.obstacles import Capsule, Sphere

        coupling = Coupling(self.mass, self.damping, self.stiffness)
        if self.kind == "grasper":
            half = 0.5 * self.jaw_length
            jaw = Capsule((-half, 0.0, 0.0), (half, 0.0, 0.0), self.radius)
            instrument = grasper([jaw], coupling, axis=(0.0, 0.0, 1.0),
                                 friction=self.friction, name=name)
        else:
            instrument = probe([Sphere((0.0, 0.0, 0.0), self.radius)], coupling, friction=self.friction, name=name)
        instrument.device, instrument.color = self.trajectory(), self.color or None
        return instrument


@dataclass
class Haptics(Options):
    """The haptic forces of the scene's instrument, logged and plotted.

    rate: the haptic loop's rate (Hz): the forces between two steps are sampled at it; max_sweeps:
    Gauss-Seidel sweeps per haptic tick (bounded time); max_contacts: the restricted problem's
    largest size."""

    rate: float = 1000.0
    max_sweeps: int = MAX_SWEEPS
    max_contacts: int = MAX_CONTACTS

    def check(self):
        require(1.0 <= self.rate <= 20_000.0, "rate", f"must be between 1 and 20000 Hz, got {self.rate}")
        require(self.max_sweeps >= 1, "max_sweeps", f"must be >= 1, got {self.max_sweeps}")
        require(self.max_contacts >= 1, "max_contacts", f"must be >= 1, got {self.max_contacts}")


class HapticsStage:
    """After the contact stage: the device's force at the step (single rate) and at the haptic
    rate until the next step (the loop's re-solve, in this process), and the jaws' poses."""

    name = "haptics"

    def __init__(self, contact_layer, settings: Haptics):
        self.stage, self.settings = contact_layer.stage, settings
        self.instruments = contact_layer.instruments
        self.solver = HapticSolver(settings.max_contacts, settings.max_sweeps)
        self.steps: list[tuple] = []       # (time, fx, fy, fz, grip, cx, cy, cz): the single-rate force
        self.ticks: list[tuple] = []       # (time, fx, fy, fz, grip, cx, cy, cz, sweeps): at the haptic rate
        self.poses: dict[str, list] = {jaw.name: [] for jaw in self.stage.jaws}
        self._sweeps = 0

    def step(self, sim) -> None:
        stage = self.stage
        instrument = stage.instruments[0]
        time, h = stage.time, stage.dt
        for jaw in stage.jaws:
            self.poses[jaw.name].append((time, jaw.R.copy(), jaw.x.copy()))
        contact = sum(jaw.impulse(stage.last.impulses) for jaw in stage.jaws) / h
        self.steps.append((time, *instrument.coupling_force(), instrument.grip_force(), *contact))
        self.solver.load(restrict(stage, sim.step_count + 1, self.settings.max_contacts))
        ticks = max(1, round(self.settings.rate * h))
        sweeps = 0
        for i in range(1, ticks + 1):
            t = time + i * h / ticks
            pose = instrument.device(t)
            f = self.solver.solve(pose.position, pose.orientation, pose.jaw)
            self.ticks.append((t, *f.force, f.grip, *f.contact, f.sweeps))
            sweeps = max(sweeps, f.sweeps)
        self._sweeps = sweeps

    def report(self) -> tuple[dict[str, float], dict[str, float]]:
        f = self.steps[-1]
        return {}, {"haptic_sweeps": self._sweeps, "haptic_contacts": self.solver.problem.n,
                    "device_force": float(np.linalg.norm(f[1:4])), "grip": f[4]}

    def drawables(self) -> list[Drawable]:
        """The jaws, at their recorded poses."""
        return [Drawable(name=jaw.name, surface=lambda bounds, o=jaw.obstacle: obstacle_surface(o, bounds),
                         pose=lambda t, n=jaw.name: self.jaw_transform(n, t), moving=True, color=instrument.color)
                for instrument in self.instruments.values() for jaw in instrument.jaws]

    def jaw_transform(self, name: str, time: float) -> np.ndarray:
        """4×4 pose of a jaw at the recorded step nearest `time` (its rest pose before the first)."""
        T = np.eye(4)
        poses = self.poses[name]
        if not poses:
            jaw = next(j for j in self.stage.jaws if j.name == name)
            T[:3, :3], T[:3, 3] = jaw.R, jaw.x
            return T
        times = np.array([p[0] for p in poses])
        _, R, x = poses[int(np.argmin(np.abs(times - time)))]
        T[:3, :3], T[:3, 3] = R, x
        return T

    def forces(self) -> tuple[np.ndarray, np.ndarray]:
        """(single-rate rows, haptic-rate rows) as arrays (see the attributes)."""
        return np.array(self.steps).reshape(-1, 8), np.array(self.ticks).reshape(-1, 9)

    def write_outputs(self, directory, figures: bool = True) -> list[Path]:
        """forces.csv (both logs) and, with `figures`, forces.png (force against time, both rates)."""
        directory = Path(directory)
        single, fast = self.forces()
        csv = directory / "forces.csv"
        rows = np.r_[np.c_[np.zeros(len(single)), single, np.zeros(len(single))], np.c_[np.ones(len(fast)), fast]]
        np.savetxt(csv, rows, delimiter=",", header="haptic_rate,time,fx,fy,fz,grip,cx,cy,cz,sweeps")
        if not figures:
            return [csv]
        png = directory / "forces.png"
        plot_forces(single, fast, png)
        return [csv, png]


def plot_forces(single: np.ndarray, fast: np.ndarray, path, title: str = "Force rendered to the device") -> None:
    """|force| and grip against time: single rate (held between steps) and haptic rate."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for ax, pick, label in ((axes[0], lambda a: np.linalg.norm(a[:, 1:4], axis=1), "|force| (N)"),
                            (axes[1], lambda a: a[:, 4], "grip (N)")):
        if len(single):
            ax.step(single[:, 0], pick(single), where="post", color="#c0392b", lw=1.2,
                    label="single rate (simulation step, held)")
        if len(fast):
            ax.plot(fast[:, 0], pick(fast), color="#2471a3", lw=0.9, label="haptic rate (re-solved per tick)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[0].set_title(title)
    axes[1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def haptics(sim) -> HapticsStage | None:
    """The stage builder: a HapticsStage when the scene declares Haptics (after the contact stage,
    which must hold the scene's instrument)."""
    declared = sim.scene.parts(Haptics)
    if not declared:
        return None
    if len(declared) > 1:
        raise TissueError(f"{', '.join(declared)}: a scene declares at most one Haptics")
    layer = next((s for s in sim.stages if s.name == "contact"), None)
    if layer is None or not getattr(layer, "instruments", None):
        raise TissueError(f"{next(iter(declared))}: haptics needs a Contact and a Tool (the instrument) in the scene")
    if len(layer.instruments) > 1:
        raise TissueError(f"{', '.join(layer.instruments)}: haptics renders one instrument; the scene has "
                          f"{len(layer.instruments)}")
    return HapticsStage(layer, next(iter(declared.values())))


add_stage(haptics, after="contact")
