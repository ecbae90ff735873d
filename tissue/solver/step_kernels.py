"""The implicit-Euler step's kernels: a step is begin (rotations, the assembled matrix, forces, the
right-hand side), CG iterations, end (the new state and the report), each over one flat argpack of
the body's arrays and a `Scheme` of the few compile-time choices.

Launches are what cost on small meshes (tens of µs each from Python), so a whole step runs in very
few kernels: "serial" runs the whole step, CG loop included, in one single-threaded kernel (best
for the paper's real-time meshes), "parallel" unrolls `unroll` CG iterations per kernel, each
iteration five parallel loops that exit early once converged. Dot products are blocked partial
sums added in a fixed order, so results are bit-identical run to run.

The kernels are module-level and read the step's parameters from an array at every launch: one
compilation per scheme serves every body, mesh size and parameter value.
"""

import functools
from dataclasses import dataclass

import taichi as ti

from .. import compilation
from ..fem import assembled, corotational
from ..fem.assembled import BLOCKS
from ..fem.corotational import FEM_WORK
from ..fem.model import DETACHED, MODEL
from ..launch import replayed
from . import multigrid, warm_start
from .multigrid import MULTIGRID_MEMBERS
from .operator import factors, multiply, operator_row, stiffness_diagonal, stiffness_times
from .parameters import DT, GX, GY, GZ, MASS_DAMPING, MAX_ITERATIONS, THRESHOLD, TOLERANCE, WARM_START
from .state import (ALPHA, BETA, BREAKDOWN, DELTA, DELTA_OLD, DONE, ITERATION, LAST_DT, NONFINITE, PQ, RES2, RHS2,
                    STATE_MEMBERS, block_nodes, blocks, sum_partials)


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


# A step's kernels take one flat argpack: the members of the model (MODEL), the FEM's work
# (FEM_WORK), the state, the assembled blocks (BLOCKS) and the multigrid. Flat, because a kernel
# reloads an ndarray's address after every store to an ndarray (they might alias), one load per
# level of nesting: measured here, a nested pack cost more than a flat one in such loops.
STEP_MEMBERS = (*MODEL.members, *FEM_WORK.members, *STATE_MEMBERS, *BLOCKS.members, *MULTIGRID_MEMBERS)
STEP = ti.types.argpack(**{name: ti.types.ndarray() for name in STEP_MEMBERS})
# The same less the multigrid's members, for the serial step of the other schemes: Taichi's CPU
# launcher sets every ndarray of a pack at each launch, replayed or not, so unread ones cost too.
PLAIN_STEP = ti.types.argpack(**{name: ti.types.ndarray() for name in STEP_MEMBERS
                                 if name not in MULTIGRID_MEMBERS})
BLOCK_MEMBERS = tuple(BLOCKS.members)


@functools.cache
def unused(members: tuple) -> dict:
    """Arrays for the members a scheme does not read (one entry each; one dict per member list)."""
    return {name: _one_entry() for name in members}


@functools.cache
def _one_entry():
    return ti.ndarray(ti.i32, 1)


# ---- kernels: a step is begin, CG iterations, end, over the launch's argpack `k` and scheme `o` ----


@ti.func
def _preconditioned(k: ti.template(), o: ti.template(), v, r):
    """z = P⁻¹ r node by node; multigrid couples nodes, so it runs after (_precondition_coupled)."""
    z = r
    if ti.static(o.preconditioner == "jacobi"):
        z = k.block_inverse[v] @ r
    return z


@ti.func
def _precondition_coupled(k: ti.template(), o: ti.template(), first):
    """For multigrid, once r is complete: z = P⁻¹ r (and p = z on the first, a value known at
    compile time or at run time), and rᵀz into partial[0] in place of the node-by-node value;
    none of it where the CG stops before (_start_cg then finds rᵀz = 0 and stops)."""
    if ti.static(o.preconditioner == "multigrid"):
        for _ in range(1):
            if not first:
                _stop_before_preconditioning(k)
            elif sum_partials(k, 1) <= k.parameters[TOLERANCE] * k.parameters[TOLERANCE] * sum_partials(k, 2):
                k.scalars[DONE] = 1     # the start meets the stopping rule (a warm one can): no V-cycle
        multigrid.apply(k, o, k.r, k.z)
        for b in range(blocks(k)):
            rz = 0.0
            if k.scalars[DONE] == 0:
                begin, end = block_nodes(k, b)
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
    return sum_partials(k, 1) <= tol * tol * k.scalars[RHS2] or iterations >= k.parameters[MAX_ITERATIONS]


@ti.func
def begin(k: ti.template(), o: ti.template(), tol):
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
    for b in range(blocks(k)):
        rz, rr = 0.0, 0.0
        begin, end = block_nodes(k, b)
        for v in range(begin, end):
            rhs = h * k.r[v] - stiffness_factor * stiffness_times(k, o, v, k.v)
            if k.held[v] != 0:
                rhs = ti.Vector([0.0, 0.0, 0.0])
            if ti.static(o.preconditioner != "none"):
                A = mass_factor * k.mass[v] * ti.Matrix.identity(float, 3) + stiffness_factor * stiffness_diagonal(k, o, v)
                if k.held[v] == DETACHED:   # no element: A is zero there, and so is r
                    A = ti.Matrix.identity(float, 3)
                k.block_inverse[v] = A.inverse()
            k.dv[v] = _guess(k, v)
            if k.parameters[WARM_START] != 0:   # CG starts from b − A dv: _warm_start preconditions it
                warm_start.take_directions(k, v, k.dv[v])
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
    nodes, and where it is not finite): the first of the directions the warm start combines."""
    guess = ti.Vector([0.0, 0.0, 0.0])
    if k.parameters[WARM_START] != 0 and k.scalars[LAST_DT] > 0 and k.held[v] == 0:
        guess = (k.parameters[DT] / k.scalars[LAST_DT]) * k.dv[v]
        if not (guess.norm_sqr() < 1e300):
            guess = ti.Vector([0.0, 0.0, 0.0])
    return guess


@ti.func
def _warm_start(k: ti.template(), o: ti.template()):
    """Warm: dv the best start within what the last steps solved (tissue.solver.warm_start), r = b − A dv,
    z = p = P⁻¹ r node by node, and rᵀz, rᵀr anew (cold, dv = 0: as they are)."""
    warm_start.combine(k, o)
    for b in range(blocks(k)):
        if k.parameters[WARM_START] != 0:
            rz, rr = 0.0, 0.0
            begin, end = block_nodes(k, b)
            for v in range(begin, end):
                products = _set_residual(k, o, v, warm_start.start_at(k, v))
                rz += products[0]
                rr += products[1]
            k.partial[0, b] = rz
            k.partial[1, b] = rr


@ti.func
def _start_cg(k: ti.template()):
    """The CG's scalars once z = P⁻¹ r is complete."""
    for _ in range(1):
        delta = sum_partials(k, 0)
        k.scalars[DELTA] = delta
        k.scalars[RHS2] = sum_partials(k, 2)
        k.scalars[ITERATION] = 0
        k.scalars[BREAKDOWN] = 0
        tol = k.parameters[TOLERANCE]
        k.scalars[DONE] = 1 if delta <= 0 or sum_partials(k, 1) <= tol * tol * k.scalars[RHS2] else 0
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
    for b in range(blocks(k)):  # q = A p (filtered), and pᵀq
        pq = 0.0
        if k.scalars[DONE] == 0:
            begin, end = block_nodes(k, b)
            for v in range(begin, end):
                qv = operator_row(k, o, v, k.p, mass_factor, stiffness_factor)
                k.q[v] = qv
                pq += k.p[v].dot(qv)
        k.partial[0, b] = pq
    for _ in range(1):
        if k.scalars[DONE] == 0:
            pq = sum_partials(k, 0)
            k.scalars[PQ] = pq
            if not (ti.abs(pq) > k.parameters[THRESHOLD]) or not (pq == pq):
                k.scalars[DONE] = 1
                if pq < 0 or not (pq == pq):
                    k.scalars[BREAKDOWN] = 1
            else:
                k.scalars[ALPHA] = k.scalars[DELTA] / pq
    for b in range(blocks(k)):  # dv += α p, r -= α q, z = P⁻¹ r, rᵀz and rᵀr
        rz, rr = 0.0, 0.0
        if k.scalars[DONE] == 0:
            alpha = k.scalars[ALPHA]
            begin, end = block_nodes(k, b)
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
            delta = sum_partials(k, 0)
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
def solve_serial(k: ti.template(), o: ti.template()):
    """CG from the right-hand side of begin to convergence, in one thread: a runtime loop whose
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
def end(k: ti.template()):
    h = k.parameters[DT]
    for b in range(blocks(k)):
        rr, bad = 0.0, 0.0
        begin, end = block_nodes(k, b)
        for v in range(begin, end):
            vel = k.v[v] + k.dv[v]
            if k.held[v] != 0:
                vel = ti.Vector([0.0, 0.0, 0.0])
            if not (vel.norm_sqr() < 1e300):  # NaN or inf
                bad += 1.0
            k.v[v] = vel
            warm_start.remember_end(k, v, vel)
            k.x[v] = k.x[v] + h * vel
            rr += k.r[v].dot(k.r[v])
        k.partial[0, b] = rr
        k.partial[1, b] = bad
    for _ in range(1):
        k.scalars[RES2] = sum_partials(k, 0)
        k.scalars[NONFINITE] = sum_partials(k, 1)


def inlines_multigrid(k, o, *_) -> bool:
    """A step kernel's instance with the multigrid V-cycle inlined: where Taichi's IR passes, chosen
    per kernel (TISSUE_ADVANCED_OPTIMIZATION=auto), are left off. They take minutes on it (many times
    the compile without them, for a step barely faster, if at all) and seconds on the other schemes'
    (bench.compile_options)."""
    return o.preconditioner == "multigrid"


@compilation.without_ir_passes(inlines_multigrid)
@ti.kernel
def _begin_parallel(k: STEP, o: ti.template(), tol: ti.f64):
    begin(k, o, tol)
    _precondition_coupled(k, o, True)
    _start_cg(k)


@compilation.without_ir_passes(inlines_multigrid)
@ti.kernel
def _iterate_parallel(k: STEP, o: ti.template()):
    for _ in ti.static(range(o.unroll)):
        _iteration(k, o)


@ti.kernel
def _end_parallel(k: STEP, o: ti.template()):
    end(k)


def _serial_kernel(pack):
    """The serial step's kernel over argpacks of `pack` (STEP; PLAIN_STEP for the schemes that read
    no multigrid)."""
    @compilation.without_ir_passes(inlines_multigrid)
    @ti.kernel
    def _serial(k: pack, o: ti.template(), part: ti.template(), tol: ti.f64):
        """The whole step ("step"), or its "begin" (up to the right-hand side) or "solve" (the CG)
        part, in one CPU thread. The report stays in the arrays (ImplicitEuler.report)."""
        ti.loop_config(serialize=True)
        for _ in range(1):
            if ti.static(part != "solve"):
                begin(k, o, tol)
            if ti.static(part != "begin"):
                solve_serial(k, o)
                end(k)

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
