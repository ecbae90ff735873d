"""CG's warm start: the start of least error in the A-norm among the combinations of what the
last steps solved and what their contact corrections changed.

A body's velocity change from one step to the next is nearly a combination of the last solves'
dv (the same loads, the elements turning slowly) and of the last contact corrections' velocity
changes (a reaction takes away, each step, what the free motion puts back: the weight pressing
on a floor, a probe's push). The start combines DIRECTIONS vectors d_i: the last solve's dv
scaled to this dt (the plain warm start's guess), the solve before it, and the velocity changes of
the last CORRECTIONS corrections (the velocities at a step's start less those its free motion
ended with). With D = [d_i], the start D c solves the Galerkin system DᵀA D c = Dᵀb, so its error
is the least in the A-norm over the span: no larger than the plain guess's (c = e₀) or than a
cold start's (c = 0), whatever the directions. The stopping rule, ‖r‖ ≤ tol ‖b‖, is unchanged.
The cost: a product with A and a pass over the nodes per direction, and a Cholesky factor of
DIRECTIONS² entries, in which a direction that adds nothing to those before it (a pivot at most
PIVOT of its diagonal: parallel to them, zero, or not finite) is left out.

The vectors are kept in the solver's `warm` array (node capacity columns): the directions, the
velocities the last free motion ended with, and the directions' products. The dot products are
blocked partial sums in the state's `partial` array, after the CG's own slots; the small system is
solved there too (in the first block's column), in runtime loops: local matrices and unrolled
loops made the step kernel's machine code, which every process makes again, a third longer.
"""

import taichi as ti

from ..fem import assembled, corotational
from .operator import factors, operator_row
from .parameters import WARM_START
from .state import block_nodes, blocks

SOLVES, CORRECTIONS = 2, 2          # the last solves' dv and corrections' velocity changes combined
DIRECTIONS = SOLVES + CORRECTIONS   # d₀ the guess, then the solves before it, then the corrections,
NEWEST_CORRECTION = SOLVES          # newest first
PIVOT = 1e-8
# Rows of the `warm` array: d_i, the velocities at the free motion's end, A d_i.
END_VELOCITY = DIRECTIONS
PRODUCTS = DIRECTIONS + 1
WARM_ROWS = 2 * DIRECTIONS + 1
# Slots of the `partial` array: the CG's (rᵀz, rᵀr, ‖b‖²); per direction i, d_iᵀb and d_mᵀA d_i for
# m ≤ i (GRAM + i (DIRECTIONS + 1) + j, j = 0 and 1 + m), summed into the first block's column
# before the solve; there too the Cholesky factor L (G = L Lᵀ), y = L⁻¹Dᵀb and the coefficients c.
GRAM = 3
FACTOR = GRAM + DIRECTIONS * (DIRECTIONS + 1)
FORWARD = FACTOR + DIRECTIONS * DIRECTIONS
COEFFICIENTS = FORWARD + DIRECTIONS
PARTIAL_ROWS = COEFFICIENTS + DIRECTIONS


@ti.func
def _multiply(k: ti.template(), o: ti.template(), src: ti.template()):
    """The product pass of `operator.multiply`, where the warm start is on (a runtime test inside the
    loops, so that the parallel schemes' loops stay parallel)."""
    if ti.static(o.operator == "matrix_free"):
        for e in range(k.counts[1]):
            if k.parameters[WARM_START] != 0:
                corotational.scatter_element(k, k, "stiffness", e, src, o.accumulation, o.rotation)
    elif ti.static(o.layout == "symmetric"):   # one thread runs the step: a runtime branch is free
        if k.parameters[WARM_START] != 0:
            assembled.symmetric_multiply(k, k, src)


@ti.func
def _direction_product(k: ti.template(), o: ti.template(), i):
    """A d_i into the warm array's products, and d_iᵀb, d_mᵀA d_i (m ≤ i) into the partial sums
    (b: in r, as `begin` leaves it); d_i passes through z, which the product reads."""
    for v in range(k.counts[0]):
        if k.parameters[WARM_START] != 0:
            k.z[v] = k.warm[i, v]
    _multiply(k, o, k.z)
    mass_factor, stiffness_factor = factors(k)
    for b in range(blocks(k)):
        if k.parameters[WARM_START] != 0:
            begin, end = block_nodes(k, b)
            s = 0.0
            for v in range(begin, end):
                q = operator_row(k, o, v, k.z, mass_factor, stiffness_factor)
                k.warm[PRODUCTS + i, v] = q
                s += k.z[v].dot(k.r[v])
            k.partial[GRAM + i * (DIRECTIONS + 1), b] = s
            for m in range(i + 1):
                s = 0.0
                for v in range(begin, end):
                    s += k.warm[m, v].dot(k.warm[PRODUCTS + i, v])
                k.partial[GRAM + i * (DIRECTIONS + 1) + 1 + m, b] = s


@ti.func
def _at(k: ti.template(), slot):
    return k.partial[slot, 0]


@ti.func
def _coefficients(k: ti.template()):
    """c with DᵀA D c = Dᵀb over the directions kept (one thread), 0 for the others: L's column
    and y's entry of a direction left out are 0."""
    for slot in range(GRAM, FACTOR):
        s = 0.0
        for b in range(blocks(k)):
            s += k.partial[slot, b]
        k.partial[slot, 0] = s
    for i in range(DIRECTIONS):
        row = GRAM + i * (DIRECTIONS + 1)
        gii = _at(k, row + 1 + i)
        pivot, t = gii, _at(k, row)
        for m in range(i):
            pivot -= _at(k, FACTOR + i * DIRECTIONS + m) ** 2
            t -= _at(k, FACTOR + i * DIRECTIONS + m) * _at(k, FORWARD + m)
        diagonal = 0.0
        if pivot > PIVOT * gii:     # (false where not finite)
            diagonal = ti.sqrt(pivot)
            t /= diagonal
        else:
            t = 0.0
        k.partial[FACTOR + i * DIRECTIONS + i, 0] = diagonal
        k.partial[FORWARD + i, 0] = t
        for j in range(i + 1, DIRECTIONS):
            s = 0.0
            if diagonal > 0:
                s = _at(k, GRAM + j * (DIRECTIONS + 1) + 1 + i)
                for m in range(i):
                    s -= _at(k, FACTOR + j * DIRECTIONS + m) * _at(k, FACTOR + i * DIRECTIONS + m)
                s /= diagonal
            k.partial[FACTOR + j * DIRECTIONS + i, 0] = s
    for back in range(DIRECTIONS):
        i = DIRECTIONS - 1 - back
        c = 0.0
        if _at(k, FACTOR + i * DIRECTIONS + i) > 0:
            c = _at(k, FORWARD + i)
            for m in range(i + 1, DIRECTIONS):
                c -= _at(k, FACTOR + m * DIRECTIONS + i) * _at(k, COEFFICIENTS + m)
            c /= _at(k, FACTOR + i * DIRECTIONS + i)
        k.partial[COEFFICIENTS + i, 0] = c


@ti.func
def take_directions(k: ti.template(), v, guess):
    """Node v's new directions: the guess, the newest correction's velocity change; all zero at a
    held node (the kept ones were taken under the held nodes of their own steps)."""
    k.warm[0, v] = guess
    k.warm[NEWEST_CORRECTION, v] = k.v[v] - k.warm[END_VELOCITY, v]
    if k.held[v] != 0:
        for i in ti.static(range(DIRECTIONS)):
            k.warm[i, v] = ti.Vector([0.0, 0.0, 0.0])


@ti.func
def combine(k: ti.template(), o: ti.template()):
    """The directions' products and the coefficients of the start, once every node took its
    directions (`take_directions`); `start_at` then takes the start node by node."""
    if ti.static(o.serial):         # one thread: the directions in a runtime loop (one copy of the code)
        for i in range(DIRECTIONS):
            _direction_product(k, o, i)
    else:                           # the loops at the kernel's top level, where they run in parallel
        for i in ti.static(range(DIRECTIONS)):
            _direction_product(k, o, i)
    for _ in range(1):
        if k.parameters[WARM_START] != 0:
            _coefficients(k)


@ti.func
def start_at(k: ti.template(), v):
    """Node v's start: dv = D c, returned r = b − A D c (b: in r); then each kind of direction
    older by one step (the guess becomes the solve before it, the newest correction the one before)."""
    dv, r = ti.Vector([0.0, 0.0, 0.0]), k.r[v]
    for i in range(DIRECTIONS):
        c = k.partial[COEFFICIENTS + i, 0]
        if c != 0:
            dv += c * k.warm[i, v]
            r -= c * k.warm[PRODUCTS + i, v]
    for back in ti.static(range(SOLVES - 1)):
        i = ti.static(SOLVES - 1 - back)
        k.warm[i, v] = k.warm[i - 1, v]
    for back in ti.static(range(CORRECTIONS - 1)):
        i = ti.static(DIRECTIONS - 1 - back)
        k.warm[i, v] = k.warm[i - 1, v]
    k.dv[v] = dv
    return r


@ti.func
def remember_end(k: ti.template(), v, velocity):
    """The velocity node v's free motion ends with (the next correction's change is measured from it)."""
    k.warm[END_VELOCITY, v] = velocity
