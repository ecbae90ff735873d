"""What a step of the implicit-Euler solver is asked to do: dt, Rayleigh damping, gravity and the
CG's stopping rule. The kernels read them from an array at every launch (`StepParameters.array`),
so a change on a live solver takes effect at the next step and compiles nothing."""

import math
from dataclasses import dataclass

import numpy as np

from ..errors import TissueError

PRECONDITIONERS = ("none", "jacobi", "multigrid")
# Slots of the parameters array the kernels read (StepParameters.array).
DT, MASS_DAMPING, STIFFNESS_DAMPING, GX, GY, GZ, TOLERANCE, THRESHOLD, MAX_ITERATIONS, WARM_START = range(10)
PARAMETERS = 10


@dataclass(frozen=True)
class CGSettings:
    """Conjugate-gradient stopping rule and preconditioner (SOFA's CGLinearSolver defaults)."""

    max_iterations: int = 25
    tolerance: float = 1e-9     # stop when ‖r‖ ≤ tolerance ‖b‖, whatever the preconditioner
    threshold: float = 1e-30    # stop when |pᵀAp| falls under it
    preconditioner: str = "none"
    # "multigrid" (tissue.solver.multigrid): coarse grid size (None: 2.5 √nodes) and
    # the degree of its Chebyshev smoother (products with A per smoothing).
    coarse_nodes: int | None = None
    smoothing_degree: int = 2
    # Start from the best combination (least A-norm error) of the last solves' dv and the last
    # contact corrections' velocity changes instead of zero (tissue.solver.warm_start); the stopping
    # rule is the same. A body at rest, in steady motion or pressed starts near its solution.
    warm_start: bool = False

    def __post_init__(self):
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise TissueError(f"max_iterations: must be an integer ≥ 1, got {self.max_iterations!r}")
        if not self.tolerance >= 0:
            raise TissueError(f"tolerance: must be ≥ 0, got {self.tolerance!r}")
        if not self.threshold >= 0:
            raise TissueError(f"threshold: must be ≥ 0, got {self.threshold!r}")
        if self.preconditioner not in PRECONDITIONERS:
            raise TissueError(f"preconditioner: unknown {self.preconditioner!r}; expected one of {PRECONDITIONERS}")
        if self.coarse_nodes is not None and not (isinstance(self.coarse_nodes, int) and self.coarse_nodes >= 8):
            raise TissueError(f"coarse_nodes: must be an integer ≥ 8 or None (automatic), got {self.coarse_nodes!r}")
        if not (isinstance(self.smoothing_degree, int) and self.smoothing_degree >= 1):
            raise TissueError(f"smoothing_degree: must be an integer ≥ 1, got {self.smoothing_degree!r}")
        if not isinstance(self.warm_start, bool):
            raise TissueError(f"warm_start: must be True or False, got {self.warm_start!r}")


@dataclass(frozen=True)
class StepParameters:
    """The parameters of a step, read by the kernels at every launch: changing them on a live
    solver takes effect at the next step and compiles nothing."""

    dt: float
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    rayleigh_mass: float = 0.0
    rayleigh_stiffness: float = 0.0
    cg: CGSettings = CGSettings()

    def __post_init__(self):
        dt = self.dt
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise TissueError(f"dt: the time step must be a finite number > 0 s, got {dt!r}")
        for name in ("rayleigh_mass", "rayleigh_stiffness"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise TissueError(f"{name}: must be a finite number ≥ 0, got {value!r}")
        if len(self.gravity) != 3 or not all(math.isfinite(g) for g in self.gravity):
            raise TissueError(f"gravity: expected 3 finite numbers, got {self.gravity!r}")

    def array(self) -> np.ndarray:
        values = np.zeros(PARAMETERS)
        values[[DT, MASS_DAMPING, STIFFNESS_DAMPING]] = self.dt, self.rayleigh_mass, self.rayleigh_stiffness
        values[[GX, GY, GZ]] = self.gravity
        values[[TOLERANCE, THRESHOLD, MAX_ITERATIONS]] = self.cg.tolerance, self.cg.threshold, self.cg.max_iterations
        values[WARM_START] = self.cg.warm_start
        return values
