"""Implicit backward Euler with one linearisation per step, solved by filtered CG.

    (M - h B - h² K) dv = h f(x, v) + h² K v,   v⁺ = v + dv,   x⁺ = x + h v⁺      (NOTES eq. 4)

with K = -Σ R Kₑ Rᵀ (the co-rotational tangent) and Rayleigh damping B = -(α_M M + α_K (-K)), so
the matrix is A = (1 + h α_M) M + (h α_K + h²) Σ R Kₑ Rᵀ. CG needs only products A p: from the
co-rotated blocks assembled once per step ("assembled", tissue.fem.assembled), or element by
element in every iteration as the paper does ("matrix_free", tissue.fem.corotational).

Launches are what cost on small meshes (tens of µs each from Python), so a whole step runs in very
few kernels: "serial" runs the whole step, CG loop included, in one single-threaded kernel (best
for the paper's real-time meshes), "parallel" unrolls `unroll` CG iterations per kernel, each
iteration five parallel loops that exit early once converged. Dot products are blocked partial sums added in a
fixed order, so results are bit-identical run to run.
"""

import math
import warnings
from dataclasses import dataclass

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem import CorotationalFEM
from ..fem.assembled import BlockRows, SymmetricBlocks
from ..fem.corotational import int_field
from ..stats import Stats
from .multigrid import Multigrid

PRECONDITIONERS = ("none", "jacobi", "multigrid")
EXECUTIONS = ("auto", "serial", "parallel")
OPERATORS = ("assembled", "matrix_free")
# On the CPU a single thread beats two below this many elements: each parallel loop costs a
# thread-pool dispatch, and a CG iteration has five of them (bench/deformation.py measures it).
SERIAL_BELOW = 30_000

# Scalar slots of the CG state kept on the device.
DELTA, DELTA0, DELTA_OLD, PQ, ALPHA, BETA, ITERATION, DONE, BREAKDOWN, RHS2, RES2, NONFINITE = range(12)


@dataclass(frozen=True)
class CGSettings:
    """Conjugate-gradient stopping rule and preconditioner (SOFA's CGLinearSolver defaults)."""

    max_iterations: int = 25
    tolerance: float = 1e-9     # stop when rᵀz ≤ tolerance² r₀ᵀz₀ (‖r‖/‖b‖ without preconditioner)
    threshold: float = 1e-30    # stop when |pᵀAp| falls under it
    preconditioner: str = "none"
    # "multigrid" (tissue.solver.multigrid): coarse grid size (None: 2.5 √nodes) and
    # the degree of its Chebyshev smoother (products with A per smoothing).
    coarse_nodes: int | None = None
    smoothing_degree: int = 2

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


@ti.data_oriented
class ImplicitEuler:
    """Time integration of one soft body. State: positions `x` and velocities `v` (Taichi fields)."""

    def __init__(self, fem: CorotationalFEM, dt: float, gravity=(0.0, 0.0, -9.81),
                 rayleigh_mass: float = 0.0, rayleigh_stiffness: float = 0.0,
                 cg: CGSettings = CGSettings(), fixed=None, execution: str = "auto",
                 operator: str = "assembled", unroll: int = 5, split_stages: bool = False):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise TissueError(f"dt: the time step must be a finite number > 0 s, got {dt!r}")
        for name, value in (("rayleigh_mass", rayleigh_mass), ("rayleigh_stiffness", rayleigh_stiffness)):
            if not (math.isfinite(value) and value >= 0):
                raise TissueError(f"{name}: must be a finite number ≥ 0, got {value!r}")
        if execution not in EXECUTIONS:
            raise TissueError(f"execution: unknown {execution!r}; expected one of {EXECUTIONS}")
        if operator not in OPERATORS:
            raise TissueError(f"operator: unknown {operator!r}; expected one of {OPERATORS}")
        if cg.preconditioner == "multigrid" and operator != "assembled":
            raise TissueError("preconditioner: 'multigrid' smooths with the assembled matrix; "
                              "use operator='assembled'")
        if fem.accumulation == "colouring":
            raise TissueError("accumulation: 'colouring' needs one launch per colour and is offered for the "
                              "force/stiffness ablation only; the solver fuses its loops with 'gather' or 'atomic'")
        be = backend.current()
        if execution == "serial" and be.arch != "cpu":
            raise TissueError(f"execution: 'serial' runs the CG in one CPU thread; on {be.arch} use "
                              "'parallel' or 'auto'")
        if execution == "auto":
            execution = "serial" if (be.arch == "cpu" and fem.n_elements < SERIAL_BELOW) else "parallel"
        self.fem, self.dt, self.cg = fem, float(dt), cg
        self.execution, self.unroll, self.operator = execution, unroll, operator
        # The serial path runs a step in one launch; split_stages times its two parts apart
        # (one more launch, ~20-40 µs on a 600-element mesh) for the benchmarks' stage tables.
        self.split_stages = split_stages
        # "assembled": Σ R Kₑ Rᵀ in 3×3 blocks once per step (the upper triangle when one thread
        # does it all, full rows otherwise); "matrix_free": element by element in every CG
        # iteration, as the paper does.
        self.matrix = None
        if operator == "assembled":
            self.matrix = (SymmetricBlocks if execution == "serial" else BlockRows)(fem)
        self.gravity = tuple(float(g) for g in gravity)
        self.rayleigh_mass, self.rayleigh_stiffness = float(rayleigh_mass), float(rayleigh_stiffness)
        self.stats = Stats()
        self._warned_inversion = False
        n, real = fem.n_nodes, be.real

        self.block = 1024 if be.arch == "cpu" else 32
        self.n_blocks = (n + self.block - 1) // self.block
        with backend.fields_of(self):
            self.x = ti.Vector.field(3, real, n)
            self.v = ti.Vector.field(3, real, n)
            self.dv = ti.Vector.field(3, real, n)
            self.r = ti.Vector.field(3, real, n)
            self.z = ti.Vector.field(3, real, n)
            self.p = ti.Vector.field(3, real, n)
            self.q = ti.Vector.field(3, real, n)
            self.external = ti.Vector.field(3, real, n)   # applied nodal forces (N), zero unless set
            self.fixed = int_field(n)
            self.scalars = ti.field(real, 12)
            self.partial = ti.field(real, (2, self.n_blocks))
            if cg.preconditioner != "none":
                self.block_inverse = ti.Matrix.field(3, 3, real, n)
        if cg.preconditioner == "multigrid":
            # By default the dense coarse product, (3 · 2.5 √n)² ≈ 56 n multiply-adds, stays under
            # the ~135 n of a product with the fine matrix.
            coarse = cg.coarse_nodes if cg.coarse_nodes is not None else max(8, round(2.5 * math.sqrt(n)))
            self.multigrid = Multigrid(self, coarse, cg.smoothing_degree)
        self.x.copy_from(fem.rest)
        self.set_fixed(fixed if fixed is not None else [])

    # ---- state at the numpy boundary --------------------------------------------------------

    def set_fixed(self, nodes) -> None:
        nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
        bad = nodes[(nodes < 0) | (nodes >= self.fem.n_nodes)]
        if len(bad):
            raise TissueError(f"fixed: node ids {bad[:10].tolist()} out of range [0, {self.fem.n_nodes})")
        mask = np.zeros(self.fem.n_nodes, dtype=np.int32)
        mask[nodes] = 1
        self.fixed.from_numpy(mask)
        self.fixed_nodes = np.flatnonzero(mask)
        if self.cg.preconditioner == "multigrid":
            self.multigrid.set_fixed(mask)

    def set_external_forces(self, forces=None) -> None:
        """Nodal forces (n, 3) in newtons applied from the next step on (tip loads, an
        instrument's push); None removes them. Forces at fixed nodes have no effect."""
        if forces is None:
            self.external.fill(0.0)
            return
        forces = np.asarray(forces, dtype=np.float64)
        if forces.shape != (self.fem.n_nodes, 3):
            raise TissueError(f"external forces: expected shape ({self.fem.n_nodes}, 3), got {forces.shape}")
        if not np.isfinite(forces).all():
            bad = np.flatnonzero(~np.isfinite(forces).all(axis=1))
            raise TissueError(f"external forces: non-finite values at nodes {bad[:10].tolist()}")
        self.external.from_numpy(forces.astype(np.float64 if self.x.dtype == ti.f64 else np.float32))

    def positions(self) -> np.ndarray:
        return self.x.to_numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        return self.v.to_numpy().astype(np.float64)

    def set_state(self, positions=None, velocities=None) -> None:
        dtype = np.float64 if self.x.dtype == ti.f64 else np.float32
        if positions is not None:
            self.x.from_numpy(np.asarray(positions, dtype=dtype))
        if velocities is not None:
            self.v.from_numpy(np.asarray(velocities, dtype=dtype))

    # ---- coefficients of A = mass_factor M + stiffness_factor Σ R Kₑ Rᵀ ------------------------

    @property
    def mass_factor(self) -> float:
        return 1.0 + self.dt * self.rayleigh_mass

    @property
    def stiffness_factor(self) -> float:
        return self.dt * self.rayleigh_stiffness + self.dt ** 2

    # ---- the step ---------------------------------------------------------------------------

    def step(self) -> None:
        """Advance one time step; raises TissueError if the state became non-finite."""
        if self.execution == "serial" and not self.split_stages:
            with self.stats.stage("step"):
                report = self._serial("step")
        else:
            with self.stats.stage("rotations+forces"):
                if self.execution == "serial":
                    self._serial("begin")
                else:
                    self._begin_parallel()
            with self.stats.stage("cg"):
                if self.execution == "serial":
                    report = self._serial("solve")
                else:
                    for _ in range(-(-self.cg.max_iterations // self.unroll)):
                        self._iterate_parallel()
                    report = self._end_parallel()
        iterations, res2, rhs2, breakdown, nonfinite, inverted = (float(c) for c in report)
        rel = math.sqrt(max(res2, 0.0) / rhs2) if rhs2 > 0 else 0.0
        self.stats.count(cg_iterations=int(iterations), cg_residual=rel, cg_breakdown=int(breakdown),
                         inverted_elements=int(inverted))
        if inverted and not self._warned_inversion:
            self._warned_inversion = True
            warnings.warn(f"{int(inverted)} elements are inverted (det F ≤ 0) at this step; linear "
                          "co-rotational elements have no inversion barrier, so the material may be too "
                          f"soft for its load (E={self.fem.material.young}) or dt too large (dt={self.dt}); "
                          "'polar' rotations recover better than 'large'", stacklevel=2)
        # A non-finite right-hand side (NaN positions, or NaN velocities at fixed nodes) stops the CG
        # at once with dv = 0, so the velocities alone would not show it.
        if nonfinite > 0 or not (math.isfinite(rhs2) and math.isfinite(res2)):
            what = (f"{int(nonfinite)} nodes have non-finite velocities" if nonfinite > 0
                    else "the forces are not finite (non-finite positions or velocities)")
            raise TissueError(f"the simulation diverged: {what} "
                              f"(dt={self.dt}, E={self.fem.material.young}, ν={self.fem.material.poisson}); "
                              "reduce dt or check the material and the constraints")

    def run(self, steps: int) -> np.ndarray:
        for _ in range(steps):
            self.step()
        return self.positions()

    # ---- kernels: a step is begin, CG iterations, end --------------------------------------

    @ti.func
    def _sum_partials(self, slot):
        s = 0.0
        for b in range(self.n_blocks):
            s += self.partial[slot, b]
        return s

    @ti.func
    def _preconditioned(self, v, r):
        """z = P⁻¹ r node by node; multigrid couples nodes, so it runs after (_precondition_coupled)."""
        z = r
        if ti.static(self.cg.preconditioner == "jacobi"):
            z = self.block_inverse[v] @ r
        return z

    @ti.func
    def multiply(self, src: ti.template()):
        """The pass that a product needs before `_stiffness_times(v, src)` can read node v."""
        if ti.static(self.operator == "assembled"):
            self.matrix.multiply(src)
        else:
            self.fem.scatter("stiffness", src)

    @ti.func
    def _precondition_coupled(self, first: ti.template()):
        """For multigrid, once r is complete: z = P⁻¹ r (and p = z on the first), and rᵀz into
        partial[0] in place of the node-by-node value."""
        if ti.static(self.cg.preconditioner == "multigrid"):
            self.multigrid.apply(self.r, self.z, self.scalars, DONE)
            for b in range(self.n_blocks):
                rz = 0.0
                if self.scalars[DONE] == 0:
                    for v in range(b * self.block, ti.min((b + 1) * self.block, self.fem.n_nodes)):
                        if ti.static(first):
                            self.p[v] = self.z[v]
                        rz += self.r[v].dot(self.z[v])
                self.partial[0, b] = rz

    @ti.func
    def operator_row(self, v, src):
        """(A src) at node v, filtered (zero at fixed nodes), after `multiply(src)`."""
        mass_factor = 1.0 + self.dt * self.rayleigh_mass
        stiffness_factor = self.dt * self.rayleigh_stiffness + self.dt * self.dt
        qv = mass_factor * self.fem.mass[v] * src[v] + stiffness_factor * self._stiffness_times(v, src)
        if self.fixed[v]:
            qv = ti.Vector([0.0, 0.0, 0.0])
        return qv

    @ti.func
    def _stiffness_times(self, v, src):
        """(Σ R Kₑ Rᵀ src) at node v, after `multiply(src)`."""
        Kp = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(self.operator == "assembled"):
            Kp = self.matrix.product_row(v, src)
        else:
            Kp = -self.fem.gathered(v)
        return Kp

    @ti.func
    def _stiffness_diagonal(self, v):
        K = ti.Matrix.zero(float, 3, 3)
        if ti.static(self.operator == "assembled"):
            K = self.matrix.diagonal_block(v)
        else:
            K = self.fem.stiffness_diagonal(v)
        return K

    @ti.func
    def _begin(self):
        h, fem = self.dt, self.fem
        mass_factor = 1.0 + h * self.rayleigh_mass
        stiffness_factor = h * self.rayleigh_stiffness + h * h
        g = ti.Vector(self.gravity)
        fem.update_rotations(self.x)
        if ti.static(self.operator == "assembled"):
            self.matrix.assemble()
        if ti.static(self.cg.preconditioner == "multigrid"):
            self.multigrid.update_rotations()
            for _ in range(1):  # the V-cycle's loops run while DONE is 0
                self.scalars[DONE] = 0
        fem.scatter("force", self.x)
        for v in range(fem.n_nodes):  # the forces f(x, v), kept in r until the right-hand side is complete
            m = fem.mass[v]
            self.r[v] = fem.gathered(v) + m * g + self.external[v] - self.rayleigh_mass * m * self.v[v]
        self.multiply(self.v)
        for b in range(self.n_blocks):
            rz, rr = 0.0, 0.0
            for v in range(b * self.block, ti.min((b + 1) * self.block, fem.n_nodes)):
                rhs = h * self.r[v] - stiffness_factor * self._stiffness_times(v, self.v)
                if self.fixed[v]:
                    rhs = ti.Vector([0.0, 0.0, 0.0])
                if ti.static(self.cg.preconditioner != "none"):
                    A = mass_factor * fem.mass[v] * ti.Matrix.identity(float, 3) \
                        + stiffness_factor * self._stiffness_diagonal(v)
                    self.block_inverse[v] = A.inverse()
                z = self._preconditioned(v, rhs)
                self.dv[v] = ti.Vector([0.0, 0.0, 0.0])
                self.r[v] = rhs
                self.z[v] = z
                self.p[v] = z
                rz += rhs.dot(z)
                rr += rhs.dot(rhs)
            self.partial[0, b] = rz
            self.partial[1, b] = rr
        self._precondition_coupled(True)
        for _ in range(1):
            delta = self._sum_partials(0)
            self.scalars[DELTA] = delta
            self.scalars[DELTA0] = delta
            self.scalars[RHS2] = self._sum_partials(1)
            self.scalars[ITERATION] = 0
            self.scalars[BREAKDOWN] = 0
            self.scalars[DONE] = 1 if delta <= 0 else 0

    @ti.func
    def _iteration(self):
        fem = self.fem
        if ti.static(self.operator == "matrix_free"):
            for e in range(fem.n_elements):  # element stage, skipped once converged
                if self.scalars[DONE] == 0:
                    fem.scatter_element("stiffness", e, self.p)
        else:
            self.matrix.multiply(self.p)  # serial only (in parallel, rows multiply on demand)
        for b in range(self.n_blocks):  # q = A p (filtered), and pᵀq
            pq = 0.0
            if self.scalars[DONE] == 0:
                for v in range(b * self.block, ti.min((b + 1) * self.block, fem.n_nodes)):
                    qv = self.operator_row(v, self.p)
                    self.q[v] = qv
                    pq += self.p[v].dot(qv)
            self.partial[0, b] = pq
        for _ in range(1):
            if self.scalars[DONE] == 0:
                pq = self._sum_partials(0)
                self.scalars[PQ] = pq
                if not (ti.abs(pq) > self.cg.threshold) or not (pq == pq):
                    self.scalars[DONE] = 1
                    if pq < 0 or not (pq == pq):
                        self.scalars[BREAKDOWN] = 1
                else:
                    self.scalars[ALPHA] = self.scalars[DELTA] / pq
        for b in range(self.n_blocks):  # dv += α p, r -= α q, z = P⁻¹ r, and rᵀz
            rz = 0.0
            if self.scalars[DONE] == 0:
                alpha = self.scalars[ALPHA]
                for v in range(b * self.block, ti.min((b + 1) * self.block, fem.n_nodes)):
                    self.dv[v] = self.dv[v] + alpha * self.p[v]  # rows are owned: no atomics
                    r = self.r[v] - alpha * self.q[v]
                    z = self._preconditioned(v, r)
                    self.r[v] = r
                    self.z[v] = z
                    rz += r.dot(z)
            self.partial[0, b] = rz
        self._precondition_coupled(False)
        for _ in range(1):
            if self.scalars[DONE] == 0:
                delta = self._sum_partials(0)
                self.scalars[DELTA_OLD] = self.scalars[DELTA]
                self.scalars[DELTA] = delta
                self.scalars[ITERATION] += 1
                self.scalars[BETA] = delta / self.scalars[DELTA_OLD]
                tol = self.cg.tolerance
                if delta <= tol * tol * self.scalars[DELTA0] or self.scalars[ITERATION] >= self.cg.max_iterations:
                    self.scalars[DONE] = 1
        for v in range(self.fem.n_nodes):
            if self.scalars[DONE] == 0:
                self.p[v] = self.z[v] + self.scalars[BETA] * self.p[v]

    @ti.func
    def _end(self):
        h = self.dt
        for b in range(self.n_blocks):
            rr, bad = 0.0, 0.0
            for v in range(b * self.block, ti.min((b + 1) * self.block, self.fem.n_nodes)):
                vel = self.v[v] + self.dv[v]
                if self.fixed[v]:
                    vel = ti.Vector([0.0, 0.0, 0.0])
                if not (vel.norm_sqr() < 1e300):  # NaN or inf
                    bad += 1.0
                self.v[v] = vel
                self.x[v] = self.x[v] + h * vel
                rr += self.r[v].dot(self.r[v])
            self.partial[0, b] = rr
            self.partial[1, b] = bad
        for _ in range(1):
            self.scalars[RES2] = self._sum_partials(0)
            self.scalars[NONFINITE] = self._sum_partials(1)

    @ti.kernel
    def _begin_parallel(self):
        self._begin()

    @ti.kernel
    def _iterate_parallel(self):
        for _ in ti.static(range(self.unroll)):
            self._iteration()

    @ti.func
    def _report(self):
        return ti.Vector([self.scalars[ITERATION], self.scalars[RES2], self.scalars[RHS2],
                          self.scalars[BREAKDOWN], self.scalars[NONFINITE], self.fem.inverted[None]])

    @ti.kernel
    def _end_parallel(self) -> ti.types.vector(6, float):
        self._end()
        return self._report()

    @ti.kernel
    def _serial(self, part: ti.template()) -> ti.types.vector(6, float):
        """The whole step ("step"), or its "begin" or "solve" part, in one CPU thread."""
        ti.loop_config(serialize=True)
        for _ in range(1):
            if ti.static(part != "solve"):
                self._begin()
            if ti.static(part != "begin"):
                while self.scalars[DONE] == 0:
                    self._iteration()
                self._end()
        return self._report()
