"""Camera presets computed from a scene's bounds.

A preset is a viewing direction relative to the scene's up axis; the distance is chosen so the
bounding box fills the image with a small margin. Pure numpy, so it is testable without a window.
"""

from __future__ import annotations

import numpy as np

from ..errors import TissueError

# (azimuth, elevation) in degrees of the direction from the scene's centre to the camera, in the
# frame (right, up, toward-viewer). 'iso' is a three-quarter view from above, the usual figure view.
PRESETS = {
    "iso": (35.0, 25.0),
    "front": (0.0, 0.0),
    "side": (90.0, 0.0),
    "top": (0.0, 90.0),
}

_AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1)}


def up_vector(up) -> np.ndarray:
    """'x', 'y', 'z' (optionally with a leading '-') or a 3-vector, as a unit vector."""
    if isinstance(up, str):
        sign = -1.0 if up.startswith("-") else 1.0
        key = up.lstrip("+-").lower()
        if key not in _AXES:
            raise TissueError(f"render: up must be 'x', 'y', 'z' (optionally signed) or a vector, got {up!r}")
        return sign * np.array(_AXES[key], dtype=float)
    v = np.asarray(up, dtype=float)
    if v.shape != (3,) or not np.linalg.norm(v) > 0:
        raise TissueError(f"render: up must be a non-zero 3-vector, got {up!r}")
    return v / np.linalg.norm(v)


def view_frame(up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Right-handed (right, up, toward-viewer) frame for an up axis.

    For y-up this is (x, y, z), the OpenGL convention; for z-up it is (x, z, -y), the
    engineering convention (front view looks along +y).
    """
    u = up_vector(up)
    # 'right' is the world axis least aligned with up (x unless up is x), made orthogonal to up.
    seed = np.eye(3)[np.argmin(np.abs(u))] if abs(u[0]) > 0.9 else np.array([1.0, 0.0, 0.0])
    right = seed - u * (seed @ u)
    right /= np.linalg.norm(right)
    toward = np.cross(right, u)
    return right, u, toward


def camera_position(bounds, preset="iso", up="y", aspect: float = 4 / 3, view_angle: float = 30.0,
                    margin: float = 1.12):
    """(position, focal point, view-up) framing `bounds` = (xmin, xmax, ymin, ymax, zmin, zmax).

    `preset` is a name of PRESETS or an (azimuth, elevation) pair in degrees. The distance is the
    smallest at which all eight corners of the box lie inside the perspective frustum of vertical
    angle `view_angle` for an image of width/height `aspect`, times `margin`.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise TissueError(f"render: unknown camera preset {preset!r}; choose one of {sorted(PRESETS)}")
        azimuth, elevation = PRESETS[preset]
    else:
        azimuth, elevation = preset
    b = np.asarray(bounds, dtype=float).reshape(3, 2)
    if not np.all(np.isfinite(b)):
        raise TissueError(f"render: cannot frame non-finite bounds {bounds}")
    centre = b.mean(axis=1)
    right, u, toward = view_frame(up)
    az, el = np.radians(azimuth), np.radians(elevation)
    direction = np.cos(el) * (np.cos(az) * toward + np.sin(az) * right) + np.sin(el) * u
    direction /= np.linalg.norm(direction)
    # Image 'up' is the scene's up projected on the image plane; looking straight down, the
    # scene's far side (-toward) is at the top of the image.
    view_up = u - direction * (u @ direction)
    if np.linalg.norm(view_up) < 1e-6:
        view_up = -toward
    view_up /= np.linalg.norm(view_up)
    image_right = np.cross(view_up, direction)  # direction points toward the camera
    corners = np.array(np.meshgrid(*b, indexing="ij")).reshape(3, -1).T - centre
    x, y, depth = corners @ image_right, corners @ view_up, corners @ direction
    tan_v = np.tan(np.radians(view_angle) / 2)
    tan_h = tan_v * aspect
    # A corner at depth d (toward the camera) is seen at distance D - d; it fits when
    # |x| <= (D - d) tan_h and |y| <= (D - d) tan_v.
    distance = max(np.max(np.abs(x) / tan_h + depth), np.max(np.abs(y) / tan_v + depth), 1e-9)
    extent = np.linalg.norm(b[:, 1] - b[:, 0])
    distance = max(distance * margin, extent * 1e-3)
    return (tuple(centre + distance * direction), tuple(centre), tuple(view_up))
