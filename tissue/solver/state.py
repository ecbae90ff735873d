"""The implicit-Euler step's state on the device, as its kernels address it: the arrays of a step's
argpack that the solver owns, the slots of the CG's scalars, and the blocks of nodes whose partial
sums make the dot products (added in a fixed order, so reruns are bit-identical)."""

import taichi as ti

# Nodal vectors, the block-diagonal inverse (preconditioners), the CG's scalars (slots below),
# blocked partial sums, the step's parameters (tissue.solver.parameters's slots), and the warm
# start's vectors (tissue.solver.warm_start).
STATE_MEMBERS = ("x", "v", "dv", "r", "z", "p", "q", "external", "block_inverse", "scalars", "partial", "parameters", "warm")
# Scalar slots of the CG state (LAST_DT: the dt of the last solve, its dv's).
DELTA, DELTA_OLD, PQ, ALPHA, BETA, ITERATION, DONE, BREAKDOWN, RHS2, RES2, NONFINITE, LAST_DT = range(12)
SCALARS = 12
# Nodes per block of the partial sums.
BLOCK = 1024


@ti.func
def blocks(k: ti.template()):
    return (k.counts[0] + BLOCK - 1) // BLOCK


@ti.func
def block_nodes(k: ti.template(), b):
    return b * BLOCK, ti.min((b + 1) * BLOCK, k.counts[0])


@ti.func
def sum_partials(k: ti.template(), slot):
    s = 0.0
    for b in range(blocks(k)):
        s += k.partial[slot, b]
    return s
