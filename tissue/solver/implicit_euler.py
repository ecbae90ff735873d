"""Implicit backward Euler with one linearisation per step, solved by filtered CG.

    (M - h B - h² K) dv = h f(x, v) + h² K v,   v⁺ = v + dv,   x⁺ = x + h v⁺      (NOTES eq. 4)

with K = -Σ R Kₑ Rᵀ (the co-rotational tangent) and Rayleigh damping B = -(α_M M + α_K (-K)), so
the matrix is A = (1 + h α_M) M + (h α_K + h²) Σ R Kₑ Rᵀ. CG needs only products A p: from the
co-rotated blocks assembled once per step ("assembled", tissue.fem.assembled), or element by
element in every iteration as the paper does ("matrix_free", tissue.fem.corotational).

This module holds the solver a body owns: its storage, the numpy boundary and the step's report.
The step's parameters (tissue.solver.parameters), its state's layout on the device
(tissue.solver.state), its matrix (tissue.solver.operator) and its kernels
(tissue.solver.step_kernels) are modules of their own.
"""

import math
import warnings
from dataclasses import replace

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem import CorotationalFEM
from ..fem.assembled import BlockRows, SymmetricBlocks
from ..fem.model import real_numpy
from ..fem.regime import check_regime
from ..launch import host_view, kept_pack, replayed
from ..stats import Stats
from .multigrid import MULTIGRID_MEMBERS, BlockJacobi, Multigrid
from .parameters import PARAMETERS, CGSettings, StepParameters
from .reference import rest_matrix
from .state import BLOCK, BREAKDOWN, ITERATION, NONFINITE, RES2, RHS2, SCALARS
from .step_kernels import (BEGIN_PARALLEL, BLOCK_MEMBERS, END_PARALLEL, ITERATE_PARALLEL, PLAIN_SERIAL, PLAIN_STEP,
                           SERIAL, STEP, Scheme, unused)
from .warm_start import PARTIAL_ROWS, WARM_ROWS

EXECUTIONS = ("auto", "serial", "parallel")
OPERATORS = ("assembled", "matrix_free")
# On the CPU a single thread beats two below this many elements: each parallel loop costs a
# thread-pool dispatch, and a CG iteration has five of them (bench/deformation.py measures it).
SERIAL_BELOW_ELEMENTS = 30_000


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
        arrays["scalars"] = ti.ndarray(real, SCALARS)
        arrays["partial"] = ti.ndarray(real, (PARTIAL_ROWS, (n + BLOCK - 1) // BLOCK))
        arrays["parameters"] = ti.ndarray(real, PARAMETERS)
        arrays["warm"] = ti.ndarray(vec3, (WARM_ROWS, n))
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
        self.forget_solves()
        self._upload_parameters()
        self.allocations += 1
        self._version = model.version

    def topology_changed(self, edit) -> None:
        self._resize()
        if self.multigrid is not None:
            self.multigrid.rebuild()

    def forget_solves(self) -> None:
        """Start the next step's CG as a new solver's first: what the warm start keeps of the last
        steps (their solves' dv, their corrections: tissue.solver.warm_start) set to zero."""
        for name in ("dv", "warm"):
            array = self.arrays[name]
            array.from_numpy(np.zeros(array.shape + (3,), dtype=real_numpy()))

    def _step_pack(self, kind=STEP):
        """The argpack of a launch (STEP, or PLAIN_STEP without the multigrid's arrays), rebuilt
        only when one of its arrays was re-allocated."""
        self._resize()
        arrays = {**self.model.arrays, **self.fem.work_arrays, **self.arrays,
                  **(self.matrix.arrays if self.matrix is not None else unused(BLOCK_MEMBERS))}
        if kind is STEP:
            arrays.update(self.multigrid.arrays if self.multigrid is not None else unused(MULTIGRID_MEMBERS))
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
        key = self.rest_key()
        made_for, matrix = self._rest_matrix
        if made_for != key:
            matrix = rest_matrix(self.model.mesh(), self.model.material, *key[2:])
            self._rest_matrix = (key, matrix)
        return matrix

    def rest_key(self) -> tuple:
        """What A₀ is a function of: the model's edits and material, dt and the damping."""
        return (self.model.edits, self.model.material, self.dt, self.rayleigh_mass, self.rayleigh_stiffness)

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
        elements), read where the step's kernels left it: on the CPU in the arrays' own memory (Taichi
        reads a kernel's return values one call at a time)."""
        scalars, inverted = self.arrays["scalars"], self.fem.work_arrays["inverted"]
        if backend.current().arch == "cpu":
            scalars, inverted = self._view(scalars), self._view(inverted)
        else:
            scalars, inverted = scalars.to_numpy(), inverted.to_numpy()
        return (scalars[ITERATION], scalars[RES2], scalars[RHS2], scalars[BREAKDOWN], scalars[NONFINITE],
                inverted[0])

    def nodal_rotations(self, tol: float):
        """The multigrid's nodal rotations of the last step (an ndarray of the node capacity:
        tissue.fem.rotations.nodal_rotation of the FEM's element rotations at `tol`) while they
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
            # Counted at the step's start: the last step's contact correction may have folded them, not
            # the free motion (liver_press's lobe: docs/performance.md, "run to its end").
            contact = ("; or, in contact, the last correction folded them: compliance warping assumes the elements "
                       "around a node turned alike (contact.compliance=exact, or a smaller dt)")
            warnings.warn(f"{int(inverted)} elements are inverted (det F ≤ 0) at this step; {why}{contact}",
                          stacklevel=3)
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


