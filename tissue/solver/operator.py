"""The implicit-Euler step's matrix A = (1 + h α_M) M + (h α_K + h²) Σ R Kₑ Rᵀ at a node, for the CG
(tissue.solver.step_kernels) and the multigrid's smoother: its products, from the co-rotated blocks
assembled once per step (tissue.fem.assembled) or element by element (tissue.fem.corotational), and
its diagonal blocks; over a step's argpack `k` and its compiled scheme `o`."""

import taichi as ti

from ..fem import assembled, corotational
from .parameters import DT, MASS_DAMPING, STIFFNESS_DAMPING


@ti.func
def multiply(k: ti.template(), o: ti.template(), src: ti.template()):
    """The pass that a product needs before `stiffness_times(v, src)` can read node v."""
    if ti.static(o.operator == "matrix_free"):
        corotational.scatter(k, k, "stiffness", src, o.accumulation, o.rotation)
    elif ti.static(o.layout == "symmetric"):
        assembled.symmetric_multiply(k, k, src)


@ti.func
def stiffness_times(k: ti.template(), o: ti.template(), v, src: ti.template()):
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
    qv = mass_factor * k.mass[v] * src[v] + stiffness_factor * stiffness_times(k, o, v, src)
    if k.held[v] != 0:
        qv = ti.Vector([0.0, 0.0, 0.0])
    return qv


@ti.func
def stiffness_diagonal(k: ti.template(), o: ti.template(), v):
    K = ti.Matrix.zero(float, 3, 3)
    if ti.static(o.operator == "matrix_free"):
        K = corotational.stiffness_diagonal(k, k, v, o.rotation)
    elif ti.static(o.layout == "symmetric"):
        K = k.diagonal[v]
    else:
        K = k.blocks[k.diagonal[v]]
    return K

