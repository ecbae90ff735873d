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
from ..body import rotation_matrix
from ..simulation import Drawable, add_stage
from .device import Trajectory
from .instrument import Coupling, Instrument, grasper, probe
from .continuity import ContinuousForce
from .lcp import MAX_CONTACTS, MAX_SWEEPS, HapticSolver, restrict


@dataclass
class Tool(Options):
    """An instrument held by a scripted device (tissue.haptics.instrument).

    kind: 'grasper' (two jaws `jaw` apart along the tool's z, each a rounded bar: a capsule of
    `radius` and `jaw_length` along the tool's x; with `jaw_width` > 0 a flat jaw instead: a box
    `jaw_length` × `jaw_width` × 2 `radius`, x by y by z) or 'probe' (a sphere of `radius`). A flat
    jaw wider than the spacing of the tissue's contact points presses them along the closing axis;
    a bar narrower than it can pass between them and push them apart sideways (`liver_grasp`).
    keyframes: (t, x, y, z, jaw opening) per key, the device's path, interpolated linearly, or
    with `smooth` eased in and out of each key (tissue.haptics.device.Trajectory); orientation:
    the tool's axes (degrees about x, y, z). mass (kg), damping (N·s/m), stiffness (N/m): the
    virtual coupling. friction: Coulomb μ of contacts on the jaws (None: the Contact's).
    """

    kind: Literal["grasper", "probe"] = "grasper"
    keyframes: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.02)
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    jaw_length: float = 0.024
    radius: float = 0.004
    jaw_width: float = 0.0
    smooth: bool = False
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
        require(self.jaw_width >= 0, "jaw_width", f"must be >= 0 m (0: a rounded bar), got {self.jaw_width}")
        require(self.mass > 0, "mass", f"must be > 0 kg, got {self.mass}")
        require(self.damping >= 0, "damping", f"must be >= 0, got {self.damping}")
        require(self.stiffness >= 0, "stiffness", f"must be >= 0, got {self.stiffness}")
        require(self.friction is None or self.friction >= 0, "friction", f"must be >= 0, got {self.friction}")

    def trajectory(self) -> Trajectory:
        return Trajectory(np.asarray(self.keyframes, dtype=np.float64).reshape(-1, 5),
                          orientation=rotation_matrix(self.orientation), smooth=self.smooth)

    def build_instrument(self, name: str) -> Instrument:
        """The instrument, its device the scripted trajectory (the contact layer calls this)."""
        from ..contact.obstacles import Box, Capsule, Sphere

        coupling = Coupling(self.mass, self.damping, self.stiffness)
        if self.kind == "grasper":
            half = 0.5 * self.jaw_length
            jaw = (Box((0.0, 0.0, 0.0), (half, 0.5 * self.jaw_width, self.radius)) if self.jaw_width > 0
                   else Capsule((-half, 0.0, 0.0), (half, 0.0, 0.0), self.radius))
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


STEP_COLUMNS = ("time", "fx", "fy", "fz", "grip", "cx", "cy", "cz", "jaw_contacts", "jaw_sliding", "organ_force",
                "obstacle_force")
# (kx, ky, kz: the part of the force that is a step's correction still being blended in, N;
# correction: Σ over the jaws of its size, N; step: the step whose problem the tick rendered, the
# hand-over being the tick where it changes; tissue.haptics.continuity)
TICK_COLUMNS = ("time", "fx", "fy", "fz", "grip", "cx", "cy", "cz", "sweeps", "residual", "kx", "ky", "kz", "correction",
                "step")
SLIDING = 0.99           # a pressed contact slides when |λ_t| >= this × μ λ_n (Coulomb's cone, to the solver's tolerance)


class HapticsStage:
    """After the contact stage: the device's force at the step (single rate) and at the haptic
    rate until the next step (the loop's re-solve, made continuous across steps, in this
    process), the jaws' poses, and what the step's contacts were doing (STEP_COLUMNS: the
    contacts pressing on the jaws and how many of them slide, the force between the soft bodies
    and that on the other obstacles, N)."""

    name = "haptics"

    def __init__(self, contact_layer, settings: Haptics):
        self.stage, self.settings = contact_layer.stage, settings
        self.instruments = contact_layer.instruments
        self.ticks_per_step = max(1, round(settings.rate * self.stage.dt))
        self.solver = ContinuousForce(HapticSolver(settings.max_contacts, settings.max_sweeps), settings.rate)
        self.steps: list[tuple] = []       # STEP_COLUMNS, per step: the single-rate force
        self.ticks: list[tuple] = []       # TICK_COLUMNS, per tick: at the haptic rate
        self.poses: dict[str, list] = {jaw.name: [] for jaw in self.stage.jaws}
        self._sweeps = 0

    def step(self, sim) -> None:
        stage = self.stage
        instrument = stage.instruments[0]
        time, h = stage.time, stage.dt
        for jaw in stage.jaws:
            self.poses[jaw.name].append((time, jaw.R.copy(), jaw.x.copy()))
        contact = sum(jaw.impulse(stage.last.impulses) for jaw in stage.jaws) / h
        self.steps.append((time, *instrument.coupling_force(), instrument.grip_force(), *contact,
                           *self._contact_state()))
        self.solver.load(restrict(stage, sim.step_count + 1, self.settings.max_contacts))
        sweeps = 0
        for i in range(1, self.ticks_per_step + 1):
            t = time + i * h / self.ticks_per_step
            pose = instrument.device(t)
            f = self.solver.solve(pose.position, pose.orientation, pose.jaw)
            self.ticks.append((t, *f.force, f.grip, *f.contact, f.sweeps, f.residual,
                               *f.correction.sum(axis=0), np.linalg.norm(f.correction, axis=1).sum(),
                               self.solver.problem.step))
            sweeps = max(sweeps, f.sweeps)
        self._sweeps = sweeps

    def _contact_state(self) -> tuple[int, int, float, float]:
        """(contacts pressing on the jaws, those of them sliding, |force| between soft bodies,
        |force| on the obstacles that are not jaws) at the last step."""
        stage, last = self.stage, self.stage.last
        if last.rows is None or not len(last.contacts):
            return 0, 0, 0.0, 0.0
        c = last.contacts
        lam = last.contact_impulses / stage.dt
        pressed = lam[:, 0] > 0
        on_jaw = stage.on_jaws(c)
        mu = stage._friction(c)
        sliding = pressed & on_jaw & (np.linalg.norm(lam[:, 1:], axis=1) >= SLIDING * mu * lam[:, 0]) & (mu > 0)
        forces = last.contact_forces
        organs = np.linalg.norm(forces[pressed & c.soft].sum(axis=0))
        obstacles = np.linalg.norm(forces[pressed & ~c.soft & ~on_jaw].sum(axis=0))
        return int((pressed & on_jaw).sum()), int(sliding.sum()), float(organs), float(obstacles)

    def problem_size(self) -> int:
        return 0 if self.solver.problem is None else self.solver.problem.n

    def report(self) -> tuple[dict[str, float], dict[str, float]]:
        f = self.steps[-1]
        return {}, {"haptic_sweeps": self._sweeps, "haptic_contacts": self.problem_size(),
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
        return (np.array(self.steps).reshape(-1, len(STEP_COLUMNS)),
                np.array(self.ticks).reshape(-1, len(TICK_COLUMNS)))

    def write_outputs(self, directory, figures: bool = True) -> list[Path]:
        """forces.csv (per step, STEP_COLUMNS), haptic_forces.csv (per tick, TICK_COLUMNS) and, with
        `figures`, forces.png (force against time at both rates, and what the contacts did)."""
        directory = Path(directory)
        single, fast = self.forces()
        written = [directory / "forces.csv", directory / "haptic_forces.csv"]
        np.savetxt(written[0], single, delimiter=",", header=",".join(STEP_COLUMNS))
        np.savetxt(written[1], fast, delimiter=",", header=",".join(TICK_COLUMNS))
        if figures:
            written.append(directory / "forces.png")
            instrument = self.stage.instruments[0]
            plot_forces(single, fast, written[-1], phases=jaw_phases(instrument.device))
        return written


def events(single: np.ndarray) -> dict[str, float]:
    """When the step log (STEP_COLUMNS) shows the grasp (the grip first over 0.1 N) and the soft
    bodies meeting after it (their contact force first over 0.1 N); NaN for what did not happen."""
    time, grip = single[:, 0], single[:, 4]
    out = {"grasp": np.nan, "liver meets stomach": np.nan}
    gripping = np.flatnonzero(grip > 0.1)
    if len(gripping):
        out["grasp"] = float(time[gripping[0]])
        meet = np.flatnonzero((single[:, 10] > 0.1) & (time > out["grasp"]))
        if len(meet):
            out["liver meets stomach"] = float(time[meet[0]])
    return out


def jaw_phases(trajectory) -> list[tuple[float, float, str]]:
    """(start, end, 'closing' | 'opening') where a Trajectory's jaw opening changes."""
    keys = getattr(trajectory, "keys", None)
    if keys is None:
        return []
    return [(a[0], b[0], "closing" if b[8] < a[8] else "opening") for a, b in zip(keys, keys[1:]) if b[8] != a[8]]


def plot_forces(single: np.ndarray, fast: np.ndarray, path, title: str = "Force rendered to the device",
                phases=()) -> None:
    """|force| and grip against time: single rate (held between steps) and haptic rate; with the
    step log's contact columns (STEP_COLUMNS), a third panel of what the contacts did and the
    events marked; `phases` (start, end, label) shaded (the jaws closing and opening)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    detailed = single.shape[1] >= len(STEP_COLUMNS)
    fig, axes = plt.subplots(3 if detailed else 2, 1, figsize=(8, 7.5 if detailed else 5.5), sharex=True)
    for ax, pick, label in ((axes[0], lambda a: np.linalg.norm(a[:, 1:4], axis=1), "|force| (N)"),
                            (axes[1], lambda a: a[:, 4], "grip (N)")):
        if len(single):
            ax.step(single[:, 0], pick(single), where="post", color="#c0392b", lw=1.2,
                    label="single rate (simulation step, held)")
        if len(fast):
            ax.plot(fast[:, 0], pick(fast), color="#2471a3", lw=0.9,
                    label="haptic rate (re-solved per tick, continuous across steps)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[0].set_title(title)
    if detailed and len(single):
        ax = axes[2]
        ax.step(single[:, 0], single[:, 10], where="post", color="#8e44ad", lw=1.1, label="liver–stomach contact force (N)")
        ax.step(single[:, 0], single[:, 11], where="post", color="#b7950b", lw=1.1, label="force on the ribs (N)")
        share = np.where(single[:, 8] > 0, single[:, 9] / np.maximum(single[:, 8], 1), 0.0)
        ax.fill_between(single[:, 0], 0, share * max(1e-9, np.max(single[:, 10:12])), step="post", color="#27ae60",
                        alpha=0.3, label="share of the jaws' contacts sliding (scaled)")
        ax.set_ylabel("contacts")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        for name, t in events(single).items():
            if np.isfinite(t):
                for a in axes:
                    a.axvline(t, color="#555555", lw=0.8, ls="--")
                axes[0].annotate(name, (t, axes[0].get_ylim()[1]), xytext=(3, -12), textcoords="offset points",
                                 fontsize=8)
    for start, end, label in phases:
        for a in axes:
            a.axvspan(start, end, color="#f4d03f" if label == "closing" else "#aed6f1", alpha=0.25, lw=0)
        axes[1].annotate(f"jaws {label}", (start, axes[1].get_ylim()[0]), xytext=(3, 4), textcoords="offset points",
                         fontsize=8)
    axes[-1].set_xlabel("time (s)")
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
