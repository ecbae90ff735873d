"""Implicit backward Euler with one linearisation per step, solved by filtered CG.

    (M - h B - h² K) dv = h f(x, v) + h² K v,   v⁺ = v + dv,   x⁺ = x + h v⁺      (NOTES eq. 4)

with K = -Σ R Kₑ Rᵀ (the co-rotational tangent) and Rayleigh damping B = -(α_M M + α_K (-K)), so
the matrix is A = (1 + h α_M) M + (h α_K + h²) Σ R Kₑ Rᵀ. CG needs only products A p: from the
co-rotated blocks assembled once per step ("assembled", tissue.fem.assembled), or element by
element in every iteration as the paper does ("matrix_free", tissue.fem.corotational).

Launches are what cost on small meshes (tens of µs each from Python), so a whole step runs in very
few kernels: "serial" runs the whole step, CG loop included, in one single-threaded kernel (best
for the paper's real-time meshes), "parallel" unrolls `unroll` CG iterations per kernel, each
iteration five parallel loops that exit early once converged. Dot products are blocked partial
sums added in a fixed order, so results are bit-identical run to run.

The kernels are module-level and take one flat argpack (STEP) of the model's arrays
(tissue.fem.model), the FEM's work, this solver's state and the step parameters (an array read at
every launch), plus a `Scheme` of the few compile-time choices: one compilation per scheme serves
every body, mesh size and parameter value.
"""

import functools
import math
import warnings
from dataclasses import dataclass, replace

import numpy as np
import taichi as ti

from .. import backend, compilation
from ..errors import TissueError
from ..fem import CorotationalFEM, assembled, corotational
from ..fem.assembled import BLOCKS, BlockRows, SymmetricBlocks
from ..fem.corotational import FEM_WORK
from ..fem.model import DETACHED, MODEL, real_numpy
from ..fem.regime import check_regime
from ..launch import host_view, kept_pack, replayed
from ..stats import Stats
from . import multigrid
from .multigrid import MULTIGRID_MEMBERS, BlockJacobi, Multigrid
from .reference import rest_matrix

PRECONDITIONERS = ("none", "jacobi", "multigrid")
EXECUTIONS = ("auto", "serial", "parallel")
OPERATORS = ("assembled", "matrix_free")
# On the CPU a single thread beats two below this many elements: each parallel loop costs a
# thread-pool dispatch, and a CG iteration has five of them (bench/deformation.py measures it).
SERIAL_BELOW_ELEMENTS = 30_000

# Scalar slots of the CG state kept on the device (LAST_DT: the dt of the last solve, its dv's).
DELTA, DELTA_OLD, PQ, ALPHA, BETA, ITERATION, DONE, BREAKDOWN, RHS2, RES2, NONFINITE, LAST_DT = range(12)


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
    # Start from the last solve's dv scaled to this dt (the same acceleration) instead of zero; the
    # stopping rule is the same. A body at rest or in steady motion starts near its solution.
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
class Scheme:
    """What a step's kernels are compiled for: a handful of choices, each a few variants, so a
    process compiles at most one kernel per combination it uses, whatever the meshes, sizes and
    parameters (a template argument of the kernels, keyed by value)."""

    rotation: str
    accumulation: str
    operator: str            # "assembled" or "matrix_free"
    layout: str              # the assembled blocks: "symmetric" (serial) or "rows" (parallel)
    preconditioner: str      # "multigrid" for block-Jacobi too, where it runs as its degenerate case
    smoothing_degree: int    # of the multigrid's Chebyshev smoother, where compiled in (parallel; 0 else)
    unroll: int              # CG iterations per launch on the parallel path

    @property
    def serial(self) -> bool:
        """One CPU thread runs the whole step (the symmetric layout's assembly would race otherwise)."""
        return self.layout == "symmetric"


# The step's state on the device: nodal vectors, the block-diagonal inverse (preconditioners),
# the CG scalars (slots above), blocked partial sums, and the step's parameters (slots below).
STATE_MEMBERS = ("x", "v", "dv", "r", "z", "p", "q", "external", "block_inverse", "scalars", "partial", "parameters")
DT, MASS_DAMPING, STIFFNESS_DAMPING, GX, GY, GZ, TOLERANCE, THRESHOLD, MAX_ITERATIONS, WARM_START = range(10)
# A step's kernels take one flat argpack: the members of the model (MODEL), the FEM's work
# (FEM_WORK), the state, the assembled blocks (BLOCKS) and the multigrid. Flat, because a kernel
# reloads an ndarray's address after every store to an ndarray (they might alias), one load per
# level of nesting: measured here, a nested pack cost ~30 % more than a flat one in such loops.
STEP_MEMBERS = (*MODEL.members, *FEM_WORK.members, *STATE_MEMBERS, *BLOCKS.members, *MULTIGRID_MEMBERS)
STEP = ti.types.argpack(**{name: ti.types.ndarray() for name in STEP_MEMBERS})
# The same less the multigrid's members, for the serial step of the other schemes: Taichi's CPU
# launcher sets every ndarray of a pack at each launch, replayed or not (~0.35 µs each).
PLAIN_STEP = ti.types.argpack(**{name: ti.types.ndarray() for name in STEP_MEMBERS
                                 if name not in MULTIGRID_MEMBERS})
BLOCK_MEMBERS = tuple(BLOCKS.members)
# Nodes per block of the partial sums (dot products summed in a fixed order: bit-identical reruns).
BLOCK = 1024


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
        values = np.zeros(10)
        values[[DT, MASS_DAMPING, STIFFNESS_DAMPING]] = self.dt, self.rayleigh_mass, self.rayleigh_stiffness
        values[[GX, GY, GZ]] = self.gravity
        values[[TOLERANCE, THRESHOLD, MAX_ITERATIONS]] = self.cg.tolerance, self.cg.threshold, self.cg.max_iterations
        values[WARM_START] = self.cg.warm_start
        return values


class ImplicitEuler:
    """Time integration of one soft body: its model (through `fem`), its state (`x`, `v`: ndarrays
    sized by the model's node capacity, the first `model.n_nodes` rows in use; `positions()` /
    `velocities()` for numpy) and the parameters of a step (`parameters`, changed with
    `set_parameters`)."""

    def __init__(self, fem: CorotationalFEM, dt: float, gravity=(0.0, 0.0, -9.81),
                 rayleigh_mass: float = 0.0, rayleigh_stiffness: float = 0.0,
                 cg: CGSettings = CGSettings(), fixed=None, execution: str = "auto",
                 operator: str = "assembled", unroll: int = 5, split_stages: bool = False):
        parameters = StepParameters(dt, tuple(float(g) for g in gravity), rayleigh_mass, rayleigh_stiffness, cg)
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
            execution = "serial" if (be.arch == "cpu" and fem.n_elements < SERIAL_BELOW_ELEMENTS) else "parallel"
        self.fem, self.model = fem, fem.model
        self.execution, self.unroll, self.operator = execution, unroll, operator
        # The serial path runs a step in one launch; split_stages times its two parts apart
        # (one more launch) for the benchmarks' stage tables.
        self.split_stages = split_stages
        # "assembled": Σ R Kₑ Rᵀ in 3×3 blocks once per step (the upper triangle when one thread
        # does it all, full rows otherwise); "matrix_free": element by element in every CG
        # iteration, as the paper does.
        layout = "symmetric" if execution == "serial" else "rows"
        self.matrix = None
        if operator == "assembled":
            self.matrix = (SymmetricBlocks if layout == "symmetric" else BlockRows)(self.model)
        # Block-Jacobi in one thread with the assembled matrix runs as the V-cycle's degenerate case
        # (multigrid.BlockJacobi): the multigrid scenes' step kernel, no instance of its own. The
        # serial V-cycle reads its smoother's degree at run time.
        coupled = cg.preconditioner == "multigrid" or (
            cg.preconditioner == "jacobi" and layout == "symmetric" and operator == "assembled")
        self.scheme = Scheme(fem.rotation, fem.accumulation, operator, layout,
                             "multigrid" if coupled else cg.preconditioner,
                             cg.smoothing_degree if layout == "rows" else 0, unroll)
        self.stats = Stats()
        self._warned_inversion = False
        self._version = None
        self._nodes = 0                # the model's nodes that the state holds
        self._node_staging = None      # set_nodes' host rows
        self.allocations = 0           # state allocations: 1, plus one per growth of the model
        self._packs = {}               # the launches' argpacks by kind (STEP, PLAIN_STEP): see _step_pack
        self.multigrid = None
        self.parameters = parameters
        self._checked_material = None     # the material check_regime last passed
        self._rest_matrix = (None, None)  # (what it was made for, A₀): see rest_matrix
        self.check_regime()
        self._resize()
        if fixed is not None:
            self.model.set_held(fixed)
        if coupled:
            self.multigrid = (Multigrid if cg.preconditioner == "multigrid" else BlockJacobi)(self)
        self.model.subscribe(self)

    @classmethod
    def with_parameters(cls, fem: CorotationalFEM, parameters: StepParameters, **options) -> "ImplicitEuler":
        """A solver for these step parameters (the scene's `Solver` group gives them)."""
        return cls(fem, **vars(parameters), **options)

    # ---- parameters ---------------------------------------------------------------------------

    @property
    def dt(self) -> float:
        return self.parameters.dt

    @property
    def gravity(self) -> tuple[float, float, float]:
        return self.parameters.gravity

    @property
    def rayleigh_mass(self) -> float:
        return self.parameters.rayleigh_mass

    @property
    def rayleigh_stiffness(self) -> float:
        return self.parameters.rayleigh_stiffness

    @property
    def cg(self) -> CGSettings:
        return self.parameters.cg

    def set_parameters(self, **changes) -> None:
        """Change dt, gravity, rayleigh_mass, rayleigh_stiffness or cg (its stopping rule) from
        the next step on. The preconditioner's kind is part of the compiled scheme: build another
        solver to change it."""
        new = replace(self.parameters, **changes)
        if (new.cg.preconditioner, new.cg.smoothing_degree, new.cg.coarse_nodes) != \
                (self.cg.preconditioner, self.cg.smoothing_degree, self.cg.coarse_nodes):
            raise TissueError("cg: the preconditioner and its multigrid settings are fixed when the solver is "
                              "built; only max_iterations, tolerance, threshold and warm_start change on a live solver")
        rest_changed = (new.dt, new.rayleigh_mass, new.rayleigh_stiffness) != \
            (self.dt, self.rayleigh_mass, self.rayleigh_stiffness)
        if new.gravity != self.gravity:
            self.check_regime(new.gravity)      # before anything changes: a refusal leaves the solver as it was
        self.parameters = new
        self._upload_parameters()
        if rest_changed and self.multigrid is not None:
            self.multigrid.retune()      # its coarse inverse is of the rest matrix at this dt

    def _upload_parameters(self) -> None:
        self.arrays["parameters"].from_numpy(self.parameters.array().astype(real_numpy()))

    # ---- storage ------------------------------------------------------------------------------

    def _resize(self) -> None:
        """Match the state to the model: nodal arrays sized by the model's node capacity (the
        kernels read the active count), re-allocated only when the model's storage grew (x, v
        and the external forces kept); nodes added since the last call join at rest, still."""
        model = self.model
        if self._version != model.version:
            self._allocate()
        if self._nodes < model.n_nodes:
            ids = np.arange(self._nodes, model.n_nodes)
            self._nodes = model.n_nodes
            self.set_nodes(ids, model.points[ids], np.zeros((len(ids), 3)))

    def _allocate(self) -> None:
        """Capacity-sized state; no compilation (the kernels take ndarrays of any size)."""
        model = self.model
        self.fem.resize()
        if self.matrix is not None:
            self.matrix.resize()
        real = backend.current().real
        vec3, mat3 = ti.types.vector(3, real), ti.types.matrix(3, 3, real)
        n = model.node_capacity
        old = getattr(self, "arrays", None)
        arrays = {name: ti.ndarray(vec3, n) for name in ("x", "v", "dv", "r", "z", "p", "q", "external")}
        arrays["block_inverse"] = ti.ndarray(mat3, n if self.scheme.preconditioner != "none" else 1)
        arrays["scalars"] = ti.ndarray(real, 12)
        arrays["partial"] = ti.ndarray(real, (3, (n + BLOCK - 1) // BLOCK))
        arrays["parameters"] = ti.ndarray(real, 10)
        for name in ("x", "v", "external"):
            values = np.zeros((n, 3), dtype=real_numpy())
            if old is not None:
                previous = old[name].to_numpy()[:self._nodes]
                values[:len(previous)] = previous
            elif name == "x":
                values[:model.n_nodes] = model.points
            arrays[name].from_numpy(values)
        if old is None:
            self._nodes = model.n_nodes
        self.arrays = arrays
        self.x, self.v = arrays["x"], arrays["v"]
        self._views = {}
        self._upload_parameters()
        self.allocations += 1
        self._version = model.version

    def topology_changed(self, edit) -> None:
        self._resize()
        if self.multigrid is not None:
            self.multigrid.rebuild()

    def _step_pack(self, kind=STEP):
        """The argpack of a launch (STEP, or PLAIN_STEP without the multigrid's arrays), rebuilt
        only when one of its arrays was re-allocated."""
        self._resize()
        arrays = {**self.model.arrays, **self.fem.work_arrays, **self.arrays,
                  **(self.matrix.arrays if self.matrix is not None else _unused(BLOCK_MEMBERS))}
        if kind is STEP:
            arrays.update(self.multigrid.arrays if self.multigrid is not None else _unused(MULTIGRID_MEMBERS))
        kept = self._packs[kind] = kept_pack(self._packs.get(kind), kind, arrays)
        return kept[0]

    # ---- state at the numpy boundary --------------------------------------------------------

    def set_fixed(self, nodes) -> None:
        self.model.set_held(nodes)
        if self.multigrid is not None:
            self.multigrid.rebuild()

    @property
    def fixed_nodes(self) -> np.ndarray:
        return self.model.held_nodes

    def set_external_forces(self, forces=None) -> None:
        """Nodal forces (n, 3) in newtons applied from the next step on (tip loads, an
        instrument's push); None removes them. Forces at fixed nodes have no effect."""
        self._resize()
        n = self.model.n_nodes
        values = np.zeros((self.model.node_capacity, 3), dtype=real_numpy())
        if forces is not None:
            forces = np.asarray(forces, dtype=np.float64)
            if forces.shape != (n, 3):
                raise TissueError(f"external forces: expected shape ({n}, 3), got {forces.shape}")
            if not np.isfinite(forces).all():
                bad = np.flatnonzero(~np.isfinite(forces).all(axis=1))
                raise TissueError(f"external forces: non-finite values at nodes {bad[:10].tolist()}")
            values[:n] = forces
        self.arrays["external"].from_numpy(values)

    def external_forces(self) -> np.ndarray:
        """The applied nodal forces (n, 3) of the next step (zeros where none were set)."""
        return self._read(self.arrays["external"])

    def positions(self) -> np.ndarray:
        return self._read(self.x)

    def velocities(self) -> np.ndarray:
        return self._read(self.v)

    def residual(self) -> np.ndarray:
        """The last solve's CG residual r = b − A dv (n, 3), in N·s: the impulse the step left
        unbalanced (tissue.solver.energy_budget bounds its work)."""
        return self._read(self.arrays["r"])

    def _read(self, array) -> np.ndarray:
        """A float64 copy of a nodal array's rows in use: on the CPU from the array's own memory
        (Taichi's to_numpy launches a parallel copy kernel, milliseconds when the cores are
        busy), elsewhere through the device."""
        self._resize()
        n = self.model.n_nodes
        if backend.current().arch == "cpu":
            return self._view(array)[:n].astype(np.float64)
        return array.to_numpy()[:n].astype(np.float64)

    def _view(self, array) -> np.ndarray:
        """numpy over a state array's memory (CPU), kept until the state is re-allocated: making
        one costs more than copying a few thousand nodes' rows."""
        kept = self._views.get(id(array))
        if kept is None:
            kept = self._views[id(array)] = (array, host_view(array))
        return kept[1]

    def set_state(self, positions=None, velocities=None) -> None:
        """Positions and velocities (n, 3) of all nodes (None: kept); on the CPU written in the
        arrays' own memory, no launch."""
        self._resize()
        n = self.model.n_nodes
        on_cpu = backend.current().arch == "cpu"
        for array, values in ((self.x, positions), (self.v, velocities)):
            if values is not None:
                padded = self._view(array) if on_cpu else np.empty((array.shape[0], 3), dtype=real_numpy())
                padded[:n] = np.asarray(values, dtype=np.float64).reshape(n, 3)
                padded[n:] = 0.0
                if not on_cpu:
                    array.from_numpy(padded)

    def set_nodes(self, ids, positions, velocities) -> None:
        """Positions and velocities (k, 3) of these nodes only (new nodes of a cut: an edit
        writes the rows it touches, not the whole state)."""
        ids = np.asarray(ids).reshape(-1)
        if len(ids) == 0:
            return
        self._resize()
        staging = self._node_staging          # host buffers reused, so the launch is replayed
        if staging is None or len(staging[0]) < len(ids):
            size = max(len(ids), 16, 2 * len(staging[0]) if staging is not None else 0)
            staging = self._node_staging = (np.empty(size, np.int32), np.empty((size, 6), real_numpy()))
        index, rows = staging
        index[len(ids):] = -1
        index[:len(ids)] = ids
        rows[:len(ids), :3] = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        rows[:len(ids), 3:] = np.asarray(velocities, dtype=np.float64).reshape(-1, 3)
        WRITE_NODES(self.x, self.v, index, rows)

    def rest_matrix(self):
        """A₀, the step matrix of the rest shape at this dt and damping (scipy CSR, every dof),
        made again only after the model or these changed: the multigrid's set-up and the contact
        compliance's A₀⁻¹ both start from it."""
        model = self.model
        key = (model.edits, model.material, self.dt, self.rayleigh_mass, self.rayleigh_stiffness)
        made_for, matrix = self._rest_matrix
        if made_for != key:
            matrix = rest_matrix(model.mesh(), model.material, *key[2:])
            self._rest_matrix = (key, matrix)
        return matrix

    # ---- coefficients of A = mass_factor M + stiffness_factor Σ R Kₑ Rᵀ ------------------------

    @property
    def mass_factor(self) -> float:
        return 1.0 + self.dt * self.rayleigh_mass

    @property
    def stiffness_factor(self) -> float:
        return self.dt * self.rayleigh_stiffness + self.dt ** 2

    # ---- the step ---------------------------------------------------------------------------

    def check_regime(self, gravity=None) -> None:
        """Refuse, with a TissueError naming the fields, the model's material under `gravity` (by
        default the solver's) outside the regime of the rotation method (tissue.fem.regime); run
        when built, before a change of gravity and before the first step after a change of
        material."""
        material = self.model.material
        check_regime(self.fem.rotation, material, self.gravity if gravity is None else gravity, self.model.points)
        self._checked_material = material

    def step(self) -> None:
        """Advance one time step; raises TissueError if the state became non-finite."""
        if self.execution == "serial" and not self.split_stages:
            plain = self.multigrid is None          # (the multigrid's V-cycle reads its arrays)
            k, o, tol = self.prepare_step(PLAIN_STEP if plain else STEP)
            with self.stats.stage("step"):
                (PLAIN_SERIAL if plain else SERIAL)(k, o, "step", tol)
        else:
            k, o, tol = self.prepare_step()
            with self.stats.stage("rotations+forces"):
                if self.execution == "serial":
                    SERIAL(k, o, "begin", tol)
                else:
                    BEGIN_PARALLEL(k, o, tol)
            with self.stats.stage("cg"):
                if self.execution == "serial":
                    SERIAL(k, o, "solve", tol)
                else:
                    for _ in range(-(-self.cg.max_iterations // self.unroll)):
                        ITERATE_PARALLEL(k, o)
                    END_PARALLEL(k, o)
        self.record_step(self.report())

    def report(self) -> tuple:
        """The last step's CG report (iterations, ‖r‖², ‖b‖², breakdown, non-finite nodes, inverted
        elements), read where the step's kernels left it: on the CPU in the arrays' own memory (a
        kernel's return costs ~1 µs a value to read)."""
        scalars, inverted = self.arrays["scalars"], self.fem.work_arrays["inverted"]
        if backend.current().arch == "cpu":
            scalars, inverted = self._view(scalars), self._view(inverted)
        else:
            scalars, inverted = scalars.to_numpy(), inverted.to_numpy()
        return (scalars[ITERATION], scalars[RES2], scalars[RHS2], scalars[BREAKDOWN], scalars[NONFINITE],
                inverted[0])

    def nodal_rotations(self, tol: float):
        """The multigrid's nodal rotations of the last step (an ndarray of the node capacity:
        tissue.fem.corotational.nodal_rotation of the FEM's element rotations at `tol`) while they
        are those of the element rotations as they are now; else None."""
        return self.multigrid.nodal_rotations(tol) if self.multigrid is not None else None

    def prepare_step(self, kind=STEP):
        """What a step's launches take: (the argpack of `kind`, the scheme, the rotations'
        tolerance), after the regime check a changed material needs (a caller fusing more into the
        serial launch, tissue.solver.step_control, takes the step through this and `record_step`)."""
        if self._checked_material is not self.model.material:
            self.check_regime()
        self.fem.rotation_writes += 1        # the launches write them (the multigrid's: see record_step)
        return self._step_pack(kind), self.scheme, self.fem.rotation_tolerance

    def record_step(self, report) -> None:
        """After a step's launch: note the nodal rotations it computed (nodal_rotations); count its CG
        report (`report`) in the stats; warn of inverted elements once; raise TissueError if the
        state became non-finite."""
        if self.multigrid is not None:
            self.multigrid.rotations_computed(self.fem.rotation_tolerance)
        iterations, res2, rhs2, breakdown, nonfinite, inverted = (float(c) for c in report)
        rel = math.sqrt(max(res2, 0.0) / rhs2) if rhs2 > 0 else 0.0
        # Ended by SOFA's denominator rule (|pᵀAp| ≤ threshold) before the residual rule or the
        # cap: a right-hand side at rounding level (a body at rest), whose relative residual
        # measures rounding, not convergence (counted apart: tissue.cli's CG line).
        cg = self.cg
        at_threshold = not breakdown and iterations < cg.max_iterations and res2 > cg.tolerance ** 2 * rhs2
        self.stats.count(cg_iterations=int(iterations), cg_residual=rel, cg_breakdown=int(breakdown),
                         cg_threshold_stop=int(at_threshold), inverted_elements=int(inverted))
        if inverted and not self._warned_inversion:
            self._warned_inversion = True
            load, step = f"E={self.fem.material.young}", f"dt={self.dt}"
            why = (f"the 'invertible' barrier did not hold them off: dt may be too large for its tangent, "
                   f"taken at the step's start ({step}), or the load past its restoring stress ({load})"
                   if self.fem.rotation == "invertible" else
                   f"linear co-rotational elements have no inversion barrier, so the material may be too soft "
                   f"for its load ({load}) or dt too large ({step}); rotation 'invertible' adds one, and "
                   "'polar' rotations recover better than 'large'")
            warnings.warn(f"{int(inverted)} elements are inverted (det F ≤ 0) at this step; {why}", stacklevel=3)
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


@ti.kernel
def _write_nodes(x: ti.types.ndarray(), v: ti.types.ndarray(), ids: ti.types.ndarray(), rows: ti.types.ndarray()):
    """x[ids[r]], v[ids[r]] = rows[r, :3], rows[r, 3:], rows whose id is −1 being padding."""
    ti.loop_config(serialize=True)    # a few rows: the thread pool would cost more
    for r in range(ids.shape[0]):
        if ids[r] >= 0:
            for c in ti.static(range(3)):
                x[ids[r]][c] = rows[r, c]
                v[ids[r]][c] = rows[r, 3 + c]


WRITE_NODES = replayed(_write_nodes)


@functools.cache
def _unused(members: tuple) -> dict:
    """Arrays for the members a scheme does not read (one entry each; one dict per member list)."""
    return {name: _one_entry() for name in members}


@functools.cache
def _one_entry():
    return ti.ndarray(ti.i32, 1)


# ---- kernels: a step is begin, CG iterations, end, over the launch's argpack `k` and scheme `o` ----


@ti.func
def _sum_partials(k: ti.template(), slot):
    s = 0.0
    for b in range((k.counts[0] + BLOCK - 1) // BLOCK):
        s += k.partial[slot, b]
    return s


@ti.func
def _blocks(k: ti.template()):
    return (k.counts[0] + BLOCK - 1) // BLOCK


@ti.func
def _block_nodes(k: ti.template(), b):
    return b * BLOCK, ti.min((b + 1) * BLOCK, k.counts[0])


@ti.func
def _preconditioned(k: ti.template(), o: ti.template(), v, r):
    """z = P⁻¹ r node by node; multigrid couples nodes, so it runs after (_precondition_coupled)."""
    z = r
    if ti.static(o.preconditioner == "jacobi"):
        z = k.block_inverse[v] @ r
    return z


@ti.func
def multiply(k: ti.template(), o: ti.template(), src: ti.template()):
    """The pass that a product needs before `_stiffness_times(v, src)` can read node v."""
    if ti.static(o.operator == "matrix_free"):
        corotational.scatter(k, k, "stiffness", src, o.accumulation, o.rotation)
    elif ti.static(o.layout == "symmetric"):
        assembled.symmetric_multiply(k, k, src)


@ti.func
def _stiffness_times(k: ti.template(), o: ti.template(), v, src: ti.template()):
    """(Σ R Kₑ Rᵀ src) at node v, after `multiply(src)`."""
    Kp = ti.Vector([0.0, 0.0, 0.0])
    if ti.static(o.operator == "matrix_free"):
        Kp = -corotational.gathered(k, k, v, o.accumulation)
    elif ti.static(o.layout == "symmetric"):
        Kp = k.product[v]
    else:
        Kp = assembled.rows_product(k, v, src)
    return Kp


@ti.func
def factors(k: ti.template()):
    """The coefficients of A = mass_factor M + stiffness_factor Σ R Kₑ Rᵀ."""
    h = k.parameters[DT]
    return 1.0 + h * k.parameters[MASS_DAMPING], h * k.parameters[STIFFNESS_DAMPING] + h * h


@ti.func
def operator_row(k: ti.template(), o: ti.template(), v, src: ti.template(), mass_factor, stiffness_factor):
    """(A src) at node v, filtered (zero at held and detached nodes), after `multiply(src)`."""
    qv = mass_factor * k.mass[v] * src[v] + stiffness_factor * _stiffness_times(k, o, v, src)
    if k.held[v] != 0:
        qv = ti.Vector([0.0, 0.0, 0.0])
    return qv


@ti.func
def _stiffness_diagonal(k: ti.template(), o: ti.template(), v):
    K = ti.Matrix.zero(float, 3, 3)
    if ti.static(o.operator == "matrix_free"):
        K = corotational.stiffness_diagonal(k, k, v, o.rotation)
    elif ti.static(o.layout == "symmetric"):
        K = k.diagonal[v]
    else:
        K = k.blocks[k.diagonal[v]]
    return K


@ti.func
def _precondition_coupled(k: ti.template(), o: ti.template(), first):
    """For multigrid, once r is complete: z = P⁻¹ r (and p = z on the first, a value known at
    compile time or at run time), and rᵀz into partial[0] in place of the node-by-node value."""
    if ti.static(o.preconditioner == "multigrid"):
        for _ in range(1):
            if not first:
                _stop_before_preconditioning(k)
        multigrid.apply(k, o, k.r, k.z)
        for b in range(_blocks(k)):
            rz = 0.0
            if k.scalars[DONE] == 0:
                begin, end = _block_nodes(k, b)
                for v in range(begin, end):
                    if first:
                        k.p[v] = k.z[v]
                    rz += k.r[v].dot(k.z[v])
            k.partial[0, b] = rz


@ti.func
def _stop_before_preconditioning(k: ti.template()):
    """The stopping rule of _next_direction, taken where _descend left ‖r‖² (partial[1]), so that
    the last iteration's V-cycle, whose z nothing reads, is skipped (one thread)."""
    if k.scalars[DONE] == 0:
        if _stops(k, k.scalars[ITERATION] + 1):
            k.scalars[ITERATION] = k.scalars[ITERATION] + 1
            k.scalars[DONE] = 1


@ti.func
def _stops(k: ti.template(), iterations):
    """CG's stopping rule: ‖r‖² (partial[1]) ≤ tol² ‖b‖², or `iterations` at the cap."""
    tol = k.parameters[TOLERANCE]
    return _sum_partials(k, 1) <= tol * tol * k.scalars[RHS2] or iterations >= k.parameters[MAX_ITERATIONS]


@ti.func
def _begin(k: ti.template(), o: ti.template(), tol):
    """Rotations, the assembled matrix, forces, the right-hand side b and CG's start: dv, r = b − A dv,
    and z = p = P⁻¹ r node by node (the coupled preconditioner and the CG's scalars follow:
    _start_cg)."""
    h = k.parameters[DT]
    mass_factor, stiffness_factor = factors(k)
    g = ti.Vector([k.parameters[GX], k.parameters[GY], k.parameters[GZ]])
    corotational.update_rotations(k, k, k.x, o.rotation, tol)
    if ti.static(o.operator == "assembled"):
        if ti.static(o.layout == "symmetric"):
            assembled.symmetric_assemble(k, k, k, o.rotation)
        else:
            assembled.rows_assemble(k, k, k, o.rotation)
    if ti.static(o.preconditioner == "multigrid"):
        multigrid.update_rotations(k, tol)
        for _ in range(1):  # the V-cycle's loops run while DONE is 0
            k.scalars[DONE] = 0
    corotational.scatter(k, k, "force", k.x, o.accumulation, o.rotation)
    for v in range(k.counts[0]):  # the forces f(x, v), kept in r until the right-hand side is complete
        mv = k.mass[v]
        k.r[v] = corotational.gathered(k, k, v, o.accumulation) + mv * g + k.external[v] \
            - k.parameters[MASS_DAMPING] * mv * k.v[v]
    multiply(k, o, k.v)
    for b in range(_blocks(k)):
        rz, rr = 0.0, 0.0
        begin, end = _block_nodes(k, b)
        for v in range(begin, end):
            rhs = h * k.r[v] - stiffness_factor * _stiffness_times(k, o, v, k.v)
            if k.held[v] != 0:
                rhs = ti.Vector([0.0, 0.0, 0.0])
            if ti.static(o.preconditioner != "none"):
                A = mass_factor * k.mass[v] * ti.Matrix.identity(float, 3) + stiffness_factor * _stiffness_diagonal(k, o, v)
                if k.held[v] == DETACHED:   # no element: A is zero there, and so is r
                    A = ti.Matrix.identity(float, 3)
                k.block_inverse[v] = A.inverse()
            k.dv[v] = _guess(k, v)
            if k.parameters[WARM_START] != 0:   # CG starts from b − A dv: _warm_start preconditions it
                k.r[v] = rhs
                rr += rhs.dot(rhs)
            else:
                products = _set_residual(k, o, v, rhs)
                rz += products[0]
                rr += products[1]
        k.partial[0, b] = rz
        k.partial[1, b] = rr
        k.partial[2, b] = rr     # ‖b‖²: the stopping rule's scale
    _warm_start(k, o)


@ti.func
def _set_residual(k: ti.template(), o: ti.template(), v, r):
    """CG's start at node v from its residual r: r, z = P⁻¹ r and p = z kept; (rᵀz, rᵀr) returned."""
    z = _preconditioned(k, o, v, r)
    k.r[v] = r
    k.z[v] = z
    k.p[v] = z
    return ti.Vector([r.dot(z), r.dot(r)])


@ti.func
def _guess(k: ti.template(), v):
    """CG's start at node v: zero, or warm, the last solve's dv scaled to this dt (zero at held
    nodes, and where it is not finite)."""
    guess = ti.Vector([0.0, 0.0, 0.0])
    if k.parameters[WARM_START] != 0 and k.scalars[LAST_DT] > 0 and k.held[v] == 0:
        guess = (k.parameters[DT] / k.scalars[LAST_DT]) * k.dv[v]
        if not (guess.norm_sqr() < 1e300):
            guess = ti.Vector([0.0, 0.0, 0.0])
    return guess


@ti.func
def _warm_start(k: ti.template(), o: ti.template()):
    """Warm: r = b − A dv, z = p = P⁻¹ r node by node, and rᵀz, rᵀr anew (cold, dv = 0: as they are)."""
    if ti.static(o.operator == "matrix_free"):
        for e in range(k.counts[1]):
            if k.parameters[WARM_START] != 0:
                corotational.scatter_element(k, k, "stiffness", e, k.dv, o.accumulation, o.rotation)
    elif ti.static(o.layout == "symmetric"):   # one thread runs the step: a runtime branch is free
        if k.parameters[WARM_START] != 0:
            assembled.symmetric_multiply(k, k, k.dv)
    mass_factor, stiffness_factor = factors(k)
    for b in range(_blocks(k)):
        if k.parameters[WARM_START] != 0:
            rz, rr = 0.0, 0.0
            begin, end = _block_nodes(k, b)
            for v in range(begin, end):
                products = _set_residual(k, o, v, k.r[v] - operator_row(k, o, v, k.dv, mass_factor, stiffness_factor))
                rz += products[0]
                rr += products[1]
            k.partial[0, b] = rz
            k.partial[1, b] = rr


@ti.func
def _start_cg(k: ti.template()):
    """The CG's scalars once z = P⁻¹ r is complete."""
    for _ in range(1):
        delta = _sum_partials(k, 0)
        k.scalars[DELTA] = delta
        k.scalars[RHS2] = _sum_partials(k, 2)
        k.scalars[ITERATION] = 0
        k.scalars[BREAKDOWN] = 0
        tol = k.parameters[TOLERANCE]
        k.scalars[DONE] = 1 if delta <= 0 or _sum_partials(k, 1) <= tol * tol * k.scalars[RHS2] else 0
        k.scalars[LAST_DT] = k.parameters[DT]


@ti.func
def _descend(k: ti.template(), o: ti.template()):
    """q = A p, α, dv += α p, r -= α q, and z = P⁻¹ r node by node (the coupled preconditioner and
    the next direction follow: _next_direction)."""
    if ti.static(o.operator == "matrix_free"):
        for e in range(k.counts[1]):  # element stage, skipped once converged
            if k.scalars[DONE] == 0:
                corotational.scatter_element(k, k, "stiffness", e, k.p, o.accumulation, o.rotation)
    elif ti.static(o.layout == "symmetric"):
        assembled.symmetric_multiply(k, k, k.p)  # serial only (rows multiply on demand)
    mass_factor, stiffness_factor = factors(k)
    for b in range(_blocks(k)):  # q = A p (filtered), and pᵀq
        pq = 0.0
        if k.scalars[DONE] == 0:
            begin, end = _block_nodes(k, b)
            for v in range(begin, end):
                qv = operator_row(k, o, v, k.p, mass_factor, stiffness_factor)
                k.q[v] = qv
                pq += k.p[v].dot(qv)
        k.partial[0, b] = pq
    for _ in range(1):
        if k.scalars[DONE] == 0:
            pq = _sum_partials(k, 0)
            k.scalars[PQ] = pq
            if not (ti.abs(pq) > k.parameters[THRESHOLD]) or not (pq == pq):
                k.scalars[DONE] = 1
                if pq < 0 or not (pq == pq):
                    k.scalars[BREAKDOWN] = 1
            else:
                k.scalars[ALPHA] = k.scalars[DELTA] / pq
    for b in range(_blocks(k)):  # dv += α p, r -= α q, z = P⁻¹ r, rᵀz and rᵀr
        rz, rr = 0.0, 0.0
        if k.scalars[DONE] == 0:
            alpha = k.scalars[ALPHA]
            begin, end = _block_nodes(k, b)
            for v in range(begin, end):
                k.dv[v] = k.dv[v] + alpha * k.p[v]  # rows are owned: no atomics
                r = k.r[v] - alpha * k.q[v]
                k.r[v] = r
                if ti.static(o.preconditioner != "multigrid"):   # (multigrid: _precondition_coupled)
                    z = _preconditioned(k, o, v, r)
                    k.z[v] = z
                    rz += r.dot(z)
                rr += r.dot(r)
        k.partial[0, b] = rz
        k.partial[1, b] = rr


@ti.func
def _next_direction(k: ti.template()):
    """β, the stopping rule, and p = z + β p, once z = P⁻¹ r is complete."""
    for _ in range(1):
        if k.scalars[DONE] == 0:
            delta = _sum_partials(k, 0)
            k.scalars[DELTA_OLD] = k.scalars[DELTA]
            k.scalars[DELTA] = delta
            k.scalars[ITERATION] = k.scalars[ITERATION] + 1
            k.scalars[BETA] = delta / k.scalars[DELTA_OLD]
            if _stops(k, k.scalars[ITERATION]):
                k.scalars[DONE] = 1
    for v in range(k.counts[0]):
        if k.scalars[DONE] == 0:
            k.p[v] = k.z[v] + k.scalars[BETA] * k.p[v]


@ti.func
def _iteration(k: ti.template(), o: ti.template()):
    _descend(k, o)
    _precondition_coupled(k, o, False)
    _next_direction(k)


@ti.func
def _solve_serial(k: ti.template(), o: ti.template()):
    """CG from the right-hand side of _begin to convergence, in one thread: a runtime loop whose
    first pass starts the CG and the others iterate, so that the preconditioner (a whole V-cycle
    for multigrid) is inlined once. The size of the kernel is what its compilation costs in every
    process (Taichi's front end, LLVM's machine code)."""
    first = 1
    while first == 1 or k.scalars[DONE] == 0:
        if first == 0:
            _descend(k, o)
        _precondition_coupled(k, o, first == 1)
        if first == 1:
            _start_cg(k)
        else:
            _next_direction(k)
        first = 0


@ti.func
def _end(k: ti.template()):
    h = k.parameters[DT]
    for b in range(_blocks(k)):
        rr, bad = 0.0, 0.0
        begin, end = _block_nodes(k, b)
        for v in range(begin, end):
            vel = k.v[v] + k.dv[v]
            if k.held[v] != 0:
                vel = ti.Vector([0.0, 0.0, 0.0])
            if not (vel.norm_sqr() < 1e300):  # NaN or inf
                bad += 1.0
            k.v[v] = vel
            k.x[v] = k.x[v] + h * vel
            rr += k.r[v].dot(k.r[v])
        k.partial[0, b] = rr
        k.partial[1, b] = bad
    for _ in range(1):
        k.scalars[RES2] = _sum_partials(k, 0)
        k.scalars[NONFINITE] = _sum_partials(k, 1)


def _multigrid(k, o, *_) -> bool:
    """A step kernel's instance with the multigrid V-cycle inlined: where Taichi's IR passes, chosen
    per kernel (TISSUE_ADVANCED_OPTIMIZATION=auto), are left off. They take minutes on it (the
    serial step: 10 -> 153 CPU s of compiling, for a step a few % faster; the parallel kernels:
    2.5x, for no faster step) and seconds on the other schemes' (bench/results/compile_options_liver19k.json)."""
    return o.preconditioner == "multigrid"


@compilation.without_ir_passes(_multigrid)
@ti.kernel
def _begin_parallel(k: STEP, o: ti.template(), tol: ti.f64):
    _begin(k, o, tol)
    _precondition_coupled(k, o, True)
    _start_cg(k)


@compilation.without_ir_passes(_multigrid)
@ti.kernel
def _iterate_parallel(k: STEP, o: ti.template()):
    for _ in ti.static(range(o.unroll)):
        _iteration(k, o)


@ti.kernel
def _end_parallel(k: STEP, o: ti.template()):
    _end(k)


def _serial_kernel(pack):
    """The serial step's kernel over argpacks of `pack` (STEP; PLAIN_STEP for the schemes that read
    no multigrid)."""
    @compilation.without_ir_passes(_multigrid)
    @ti.kernel
    def _serial(k: pack, o: ti.template(), part: ti.template(), tol: ti.f64):
        """The whole step ("step"), or its "begin" (up to the right-hand side) or "solve" (the CG)
        part, in one CPU thread. The report stays in the arrays (ImplicitEuler.report)."""
        ti.loop_config(serialize=True)
        for _ in range(1):
            if ti.static(part != "solve"):
                _begin(k, o, tol)
            if ti.static(part != "begin"):
                _solve_serial(k, o)
                _end(k)

    return _serial


SERIAL, PLAIN_SERIAL, BEGIN_PARALLEL, ITERATE_PARALLEL, END_PARALLEL = (
    replayed(kernel) for kernel in (_serial_kernel(STEP), _serial_kernel(PLAIN_STEP), _begin_parallel,
                                    _iterate_parallel, _end_parallel))


@ti.kernel
def apply_preconditioner(k: STEP, o: ti.template(), r: ti.types.ndarray(), z: ti.types.ndarray()):
    """z = B r alone (tests): the multigrid V-cycle with the matrix of the last step."""
    for _ in range(1):
        k.scalars[DONE] = 0
    if ti.static(o.serial):   # a one-thread scheme's V-cycle: serial loops
        ti.loop_config(serialize=True)
        for _ in range(1):
            multigrid.apply(k, o, r, z)
    else:
        multigrid.apply(k, o, r, z)
