"""tissue: real-time soft-tissue simulation (co-rotational implicit FEM in Taichi)."""

from .errors import TissueError

__version__ = "0.1.0"
__all__ = ["TissueError", "__version__"]
