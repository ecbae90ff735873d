"""Offscreen, figure-ready rendering of soft bodies and obstacles (pyvista), with PNG/GIF/MP4 writers.

Importing this package imports pyvista; `import tissue` does not.
"""

import ctypes.util
import os

# Without a display VTK first tries X, logs "bad X server connection", then falls back to EGL. Ask
# for EGL directly when it is there; otherwise leave VTK's own choice (OSMesa), since a window
# class that cannot load crashes the process rather than raising.
if not os.environ.get("DISPLAY") and ctypes.util.find_library("EGL"):
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

from .camera import PRESETS, camera_position  # noqa: E402
from .renderer import Animation, Renderer  # noqa: E402
from .writers import GifWriter, Mp4Writer, write_png  # noqa: E402

__all__ = ["Renderer", "Animation", "PRESETS", "camera_position", "write_png", "GifWriter", "Mp4Writer"]
