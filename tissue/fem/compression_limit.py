"""The compression limit of "invertible" rotations: a barrier on each principal stretch of an
element's rotated deformation below COMPRESSION_LIMIT, its energy, stress and tangent, as Taichi
functions for the FEM's kernels (tissue.fem.corotational) and the energy (tissue.fem.energy).
"""

import taichi as ti

from .rotations import symmetric_eigen

# The compression limit of "invertible": below COMPRESSION_LIMIT c, a principal stretch σ̂ of the
# rotated deformation RᵀF = V Σ̂ Vᵀ (σ̂ negative in an inverted element) pays the extra energy
# V ψ(σ̂), ψ(σ̂) = κ c² φ(σ̂/c) with κ = COMPRESSION_STIFFNESS (λ + 2μ) and the barrier
# φ(s) = (s − 1)²/(2s): its expansion to second order at s = 1 is κ/2 (σ̂ − c)² (the quadratic
# limit this replaced), and its energy and stress grow without bound as the element flattens
# (σ̂ → 0), as a hyperelastic volumetric term's do. The quadratic limit's stress stayed finite,
# κ c = 3 (λ + 2μ) at σ̂ = 0: under a load of the order of E (the 240-tet cantilever hanging at
# E = 1e2 Pa) it held the clamp's corner elements at det F ≈ 0.005 at rest, and any swing flipped
# them. Below s = BARRIER_END (nearly flat, or inverted) φ is continued by its tangent line at
# BARRIER_END (Irving et al. 2004 clamp the stretches at a threshold the same way), so an inverted
# element has a finite energy and a constant restoring stress, ψ'(BARRIER_END c) = −21.7 κ c: the
# most the barrier can resist with. The barrier so spans 70 % to 95.5 % compression. At 0.3 (cap
# −5.1 κ c) the hanging cantilever at E 1e2 Pa (ρgL/E = 9.8) rested on the cap: its clamp's
# elements, three nodes held and one free, stood at σ̂ = 0.083 < 0.09 = the cap's stretch, and the
# swing's extra tension pulled their free node through the clamp's plane (10 elements flipped at
# the swing's lowest point). In the invertible material cells of bench/stability.py, steps ending
# with an element inverted (cells starting with none; `inverted_steps`): 639 of 13,400 at 0.3
# (E 1e2 Pa, ν ≤ 0.3: 249-297 of 1,000 at dt 1 ms, where the step's linearisation is exact enough),
# 34 at 0.2 (20 at dt 1 ms), 9 at 0.15, 1-3 steps a cell, all at dt ≥ 0.04 s (the barrier's
# tangent is taken at the step's start); every cell bounded in these runs. At 0.1, long before
# (a stress growing with the inversion too), the 10 m/s floor impact at dt 0.04 s gained 700
# energy scales to 1e31 (the contact correction crushed elements): that cell is refused now
# (tissue.fem.regime), and its 2 ms cell is bounded at 0.15.
# Rational, not a logarithm: float64 log is missing on some backends (Vulkan's GLSL).
# Linear co-rotational energy alone is finite at σ̂ = 0, so a load of the order of E leaves
# elements inverted at its minimum (the hanging cantilever at E = 1e2 Pa, ν = 0.3: 156 of 240).
COMPRESSION_LIMIT = 0.3
COMPRESSION_STIFFNESS = 10.0
BARRIER_END = 0.15


@ti.func
def compressed(S):
    """Whether the symmetric S has an eigenvalue below the compression limit c: S − cI is not
    positive definite (Sylvester's leading minors), a few flops for the common case."""
    c = COMPRESSION_LIMIT
    a, d, f = S[0, 0] - c, S[1, 1] - c, S[2, 2] - c
    minor2 = a * d - S[0, 1] * S[0, 1]
    det = a * (d * f - S[1, 2] * S[1, 2]) - S[0, 1] * (S[0, 1] * f - S[1, 2] * S[0, 2]) \
        + S[0, 2] * (S[0, 1] * S[1, 2] - d * S[0, 2])
    return not (a > 0.0 and minor2 > 0.0 and det > 0.0)


@ti.func
def limit_stiffness(m: ti.template(), e):
    """κ of the compression limit: COMPRESSION_STIFFNESS (λ + 2μ)."""
    return COMPRESSION_STIFFNESS * (m.elastic[e][1] + 2.0 * m.elastic[e][2])


@ti.func
def limit_slope_curvature(kappa, value):
    """ψ'(σ̂) and ψ''(σ̂) of the compression limit at one principal stretch σ̂ = `value` (both zero
    at and above c): κ c φ'(s) and κ φ''(s), s = σ̂/c, with φ' = (1 − 1/s²)/2, φ'' = 1/s³ down to
    BARRIER_END, and φ' held at its value there (φ'' = 0) below."""
    c = COMPRESSION_LIMIT
    s = value / c
    slope, curvature = 0.0, 0.0
    if s < 1.0:
        t = ti.max(s, BARRIER_END)
        slope = kappa * c * 0.5 * (1.0 - 1.0 / (t * t))
        if s >= BARRIER_END:
            curvature = kappa / (t * t * t)
    return slope, curvature


@ti.func
def limit_energy(kappa, value):
    """ψ(σ̂) = κ c² φ(σ̂/c) of the compression limit at one principal stretch (zero above c)."""
    c = COMPRESSION_LIMIT
    s = value / c
    energy = 0.0
    if s < 1.0:
        t = ti.max(s, BARRIER_END)
        h = s - t
        energy = kappa * c * c * ((t - 1.0) ** 2 / (2.0 * t) + 0.5 * (1.0 - 1.0 / (t * t)) * h)
    return energy


@ti.func
def limited_directions(m: ti.template(), e, S):
    """The eigenvectors of the symmetric S whose eigenvalue is below the limit, as columns (the
    others zero), and the limit's curvature ψ'' along each."""
    values, V = symmetric_eigen(S)
    D = ti.Matrix.zero(float, 3, 3)
    k = ti.Vector([0.0, 0.0, 0.0])
    kappa = limit_stiffness(m, e)
    for i in ti.static(range(3)):
        if values[i] < COMPRESSION_LIMIT:
            _, k[i] = limit_slope_curvature(kappa, values[i])
            for j in ti.static(range(3)):
                D[j, i] = V[j, i]
    return D, k


@ti.func
def limit_tangent_stress(w: ti.template(), e, G):
    """The compression limit's tangent: Σᵢ ψ''(σ̂ᵢ) (dᵢᵀ ε dᵢ) dᵢ dᵢᵀ over its active directions dᵢ
    (the directions held fixed over the step, as the rotation is)."""
    D = w.limited[e]
    P = ti.Matrix.zero(float, 3, 3)
    if D.norm_sqr() > 0.0:
        k = w.limit_curvature[e]
        eps = 0.5 * (G + G.transpose())
        for i in ti.static(range(3)):
            d = ti.Vector([D[0, i], D[1, i], D[2, i]])
            P += k[i] * d.dot(eps @ d) * d.outer_product(d)
    return P


@ti.func
def compression_stress(m: ti.template(), e, S):
    """The compression limit's stress in the rotated frame, Σᵢ ψ'(σ̂ᵢ) vᵢ vᵢᵀ, for
    S = sym(RᵀF) = V Σ̂ Vᵀ: the derivative of V Σᵢ ψ(σ̂ᵢ), whose gradient in F is
    R V diag(ψ'(σ̂ᵢ)) Vᵀ (Irving et al. 2004, P = U P̂(Σ̂) Vᵀ). Pushes an inverted element's
    negative σ̂ back up through zero."""
    kappa = limit_stiffness(m, e)
    values, V = symmetric_eigen(S)
    P = ti.Matrix.zero(float, 3, 3)
    for i in ti.static(range(3)):
        vi = ti.Vector([V[0, i], V[1, i], V[2, i]])
        slope, _ = limit_slope_curvature(kappa, values[i])
        P += slope * vi.outer_product(vi)
    return P
