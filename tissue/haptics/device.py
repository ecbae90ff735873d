"""Haptic devices: a small protocol, a scripted device, and a UDP bridge for real devices.

Protocol (any object with these two methods):

    read(time) -> DevicePose      the device's pose (tip position, orientation, jaw opening) now;
                                  `time` is the haptic loop's clock (s), which a scripted device
                                  follows and a real one ignores
    send(time, force, grip)       the force to render (N, world frame, (3,)) and the grip (N, the
                                  squeeze on the jaws; > 0: something between them resists closing)

ScriptedDevice follows a Trajectory (keyframes, or a file of timestamped poses) and logs the forces
it is sent. UdpDevice is the simulation's end of a bridge over UDP on 127.0.0.1: a driver for a
real device (OpenHaptics, Force Dimension, CHAI3D…) runs a small client (DeviceClient, or the same
packets from C) that sends the device's pose and receives the force.

Packets (little-endian, fixed size, one per datagram):

    pose   80 bytes  b"TPOS", uint32 sequence, float64 time, float64 x, y, z (m),
                     float64 qw, qx, qy, qz (unit quaternion: the tool's axes), float64 jaw (m)
    force  48 bytes  b"TFRC", uint32 sequence (of the last pose received), float64 time,
                     float64 fx, fy, fz (N), float64 grip (N)

The bridge keeps the newest pose (a datagram that arrives late is older, not lost work) and
answers the address the last pose came from.
"""

from __future__ import annotations

import bisect
import socket
import struct
from pathlib import Path

import numpy as np

from ..errors import TissueError
from .instrument import DevicePose

POSE = struct.Struct("<4sId3d4dd")
FORCE = struct.Struct("<4sId3dd")
POSE_TAG, FORCE_TAG = b"TPOS", b"TFRC"


def quaternion_to_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quaternion(R) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    if w > 1e-6:
        v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (4 * w)
        return np.r_[w, v]
    i = int(np.argmax(np.diagonal(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = np.sqrt(max(0.0, 1.0 + R[i, i] - R[j, j] - R[k, k])) * 2.0
    q = np.zeros(4)
    q[0], q[1 + i] = (R[k, j] - R[j, k]) / s, s / 4.0
    q[1 + j], q[1 + k] = (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    return q


class Trajectory:
    """Timestamped poses, interpolated linearly (position, jaw; orientation: the last key's at or
    before the time), held before the first and after the last.

    keys: (k, 9) rows t, x, y, z, qw, qx, qy, qz, jaw, or (k, 5) rows t, x, y, z, jaw (orientation:
    `orientation`, identity by default). A file (`Trajectory.load`): .npy or .csv of such rows.
    smooth: ease in and out of every key (smoothstep, 3w² − 2w³, along each segment), as a hand
    moves from pose to pose: the device's velocity is continuous, zero at the keys, where the
    linear path's jumps kick the instrument's jaws into whatever they touch."""

    def __init__(self, keys, orientation=None, smooth: bool = False):
        keys = np.asarray(keys, dtype=np.float64)
        if keys.ndim != 2 or keys.shape[1] not in (5, 9) or len(keys) == 0:
            raise TissueError(f"trajectory: expected rows (t, x, y, z, jaw) or (t, x, y, z, qw, qx, qy, qz, jaw), "
                              f"got shape {keys.shape}")
        if not np.all(np.isfinite(keys)):
            raise TissueError("trajectory: keys must be finite")
        if np.any(np.diff(keys[:, 0]) <= 0):
            raise TissueError(f"trajectory: times must increase, got {keys[:, 0].tolist()}")
        if keys.shape[1] == 5:
            q = matrix_to_quaternion(np.eye(3) if orientation is None else orientation)
            keys = np.column_stack([keys[:, :4], np.tile(q, (len(keys), 1)), keys[:, 4]])
        self.keys, self.smooth = keys, smooth
        self._times = keys[:, 0].tolist()
        self._R = [quaternion_to_matrix(k[4:8]) for k in keys]

    @staticmethod
    def load(path) -> "Trajectory":
        path = Path(path)
        if not path.is_file():
            raise TissueError(f"{path}: no such trajectory file")
        try:
            keys = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, delimiter=",", ndmin=2)
        except ValueError as err:
            raise TissueError(f"{path}: not a table of numbers ({err})") from None
        try:
            return Trajectory(keys)
        except TissueError as err:
            raise TissueError(f"{path}: {err}") from None

    def save(self, path) -> None:
        path = Path(path)
        if path.suffix == ".npy":
            np.save(path, self.keys)
        else:
            np.savetxt(path, self.keys, delimiter=",", header="t,x,y,z,qw,qx,qy,qz,jaw")

    def __call__(self, time: float) -> DevicePose:
        # (Called every haptic tick: a bisection and one lerp of a row, cheaper than np.interp per column.)
        times, k = self._times, self.keys
        i = bisect.bisect_right(times, time) - 1
        if i < 0:
            row, i = k[0], 0
        elif i >= len(times) - 1:
            row, i = k[-1], len(times) - 1
        else:
            w = (time - times[i]) / (times[i + 1] - times[i])
            if self.smooth:
                w = w * w * (3.0 - 2.0 * w)
            row = k[i] + w * (k[i + 1] - k[i])
        return DevicePose(row[1:4].copy(), self._R[i], float(row[8]), float(time))


class ScriptedDevice:
    """A device that follows a trajectory (a Trajectory, a function time -> DevicePose, or a file)
    and logs what it is sent: `log` rows (time, fx, fy, fz, grip)."""

    def __init__(self, trajectory):
        if isinstance(trajectory, (str, Path)):
            trajectory = Trajectory.load(trajectory)
        if not callable(trajectory):
            raise TissueError(f"ScriptedDevice: expected a trajectory, a function of time or a file, "
                              f"got {type(trajectory).__name__}")
        self.trajectory = trajectory
        self.log: list[tuple] = []

    def read(self, time: float) -> DevicePose:
        return self.trajectory(time)

    def send(self, time: float, force, grip: float) -> None:
        self.log.append((time, *np.asarray(force, dtype=np.float64), grip))

    def forces(self) -> np.ndarray:
        """(k, 5) the log as an array."""
        return np.array(self.log).reshape(-1, 5)


class UdpDevice:
    """The simulation's end of the UDP bridge on 127.0.0.1 (see the module docstring): `read`
    returns the newest pose received (`initial` until the first), `send` answers the client.
    The socket is bound on first use (so the object can be handed to the haptic loop's process)."""

    def __init__(self, port: int, initial: DevicePose | None = None):
        if not (isinstance(port, int) and 0 < port < 65536):
            raise TissueError(f"haptic bridge: port must be in 1..65535, got {port!r}")
        self.port, self.socket = port, None
        self.pose = initial if initial is not None else DevicePose.at((0.0, 0.0, 0.0))
        self.sequence, self.client, self.received = 0, None, 0

    def open(self) -> None:
        if self.socket is not None:
            return
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.socket.bind(("127.0.0.1", self.port))
        except OSError as err:
            self.socket = None
            raise TissueError(f"haptic bridge: cannot bind 127.0.0.1:{self.port} ({err.strerror})") from None
        self.socket.setblocking(False)

    def read(self, time: float) -> DevicePose:
        self.open()
        while True:
            try:
                data, address = self.socket.recvfrom(256)
            except BlockingIOError:
                return self.pose
            if len(data) != POSE.size or data[:4] != POSE_TAG:
                continue                                 # not ours: ignored
            _, sequence, t, x, y, z, qw, qx, qy, qz, jaw = POSE.unpack(data)
            if self.client is not None and address == self.client and sequence < self.sequence:
                continue                                 # older than what we have
            self.pose = DevicePose(np.array([x, y, z]), quaternion_to_matrix((qw, qx, qy, qz)), jaw, t)
            self.sequence, self.client = sequence, address
            self.received += 1

    def send(self, time: float, force, grip: float) -> None:
        if self.client is None or self.socket is None:
            return
        f = np.asarray(force, dtype=np.float64)
        try:
            self.socket.sendto(FORCE.pack(FORCE_TAG, self.sequence, time, f[0], f[1], f[2], grip), self.client)
        except OSError:
            pass                                         # a client gone: the next pose brings it back

    def close(self) -> None:
        if self.socket is not None:
            self.socket.close()
            self.socket = None


class DeviceClient:
    """A driver's end of the bridge: sends poses, receives forces (a template for a real driver)."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.address = (host, int(port))
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.socket.bind(("127.0.0.1", 0))
        self.sequence = 0

    def send_pose(self, time: float, position, orientation=None, jaw: float = 0.0) -> None:
        self.sequence += 1
        q = matrix_to_quaternion(np.eye(3) if orientation is None else orientation)
        p = np.asarray(position, dtype=np.float64)
        self.socket.sendto(POSE.pack(POSE_TAG, self.sequence, time, *p, *q, jaw), self.address)

    def receive_force(self, timeout: float = 1.0):
        """(sequence, time, force (3,), grip) of the next force packet, or None after `timeout` s."""
        self.socket.settimeout(timeout)
        try:
            data = self.socket.recv(256)
        except (socket.timeout, BlockingIOError):
            return None
        if len(data) != FORCE.size or data[:4] != FORCE_TAG:
            return None
        _, sequence, t, fx, fy, fz, grip = FORCE.unpack(data)
        return sequence, t, np.array([fx, fy, fz]), grip

    def close(self) -> None:
        self.socket.close()
