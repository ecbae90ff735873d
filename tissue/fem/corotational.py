"""Co-rotational linear tetrahedra (Felippa 2000; paper §2): element rotations, elastic forces and
stiffness products, accumulated element -> node in one of three ways.

Rotations: "large" (edge frames, SOFA's), "polar" (of F = R S; for an inverted element the closest
proper rotation, F = U Σ̂ Vᵀ with the smallest singular value negative and R = U Vᵀ: Irving et al.
2004), "invertible" ("polar" plus a compression limit in that diagonal frame, see
`compression_stress`) and "linear" (none).

Per element we keep only the rest shape's inverse edge matrix `Dm⁻¹`, the volume, the Lamé
parameters and the current rotation `R` (20 numbers), not the 12×12 stiffness: the product `Kₑ u`
is computed as stress from strain, `f_a = -V R σ(ε(Rᵀ u)) g_a`, which is exactly `R Kₑ Rᵀ u` for the
linear tetrahedron and moves far fewer bytes.

Accumulation (paper Fig. 3):
  gather    one thread per element writes its 4 nodal vectors to a per-element buffer, then one
            thread per vertex sums its incident entries in a fixed order (deterministic);
  atomic    one thread per element adds to the nodes atomically;
  colouring elements are split into colours that share no node; one parallel loop per colour.
"""


import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..mesh import TetMesh
from .material import Material
from .model import MODEL, BodyModel, real_numpy

# The per-step work of the FEM: element rotations, the principal directions (columns, rotated
# frame) in which each element's compression limit is active ("invertible"; zero otherwise) and
# the limit's curvature ψ''(σ̂) along each, the inverted-element count, and the gather buffer (4
# per element) or the atomic accumulator (per node), whichever the accumulation uses.
FEM_WORK = ti.types.argpack(R=ti.types.ndarray(), limited=ti.types.ndarray(), limit_curvature=ti.types.ndarray(),
                            inverted=ti.types.ndarray(), buffer=ti.types.ndarray(), accumulator=ti.types.ndarray())

ROTATIONS = ("large", "polar", "invertible", "linear")
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
# The mean of a node's element rotations is taken as singular (no polar factor) below this
# determinant (1 for alike rotations; 0 when, e.g., I and a half turn average).
SINGULAR_MEAN = 1e-6
# An element whose |det F| is at most this is (nearly) flat: its polar rotation is ill-defined, so it
# takes its edge frame's ("large") rotation instead.
FLAT_DETERMINANT = 1e-6
COMPRESSION_LIMIT = 0.3
COMPRESSION_STIFFNESS = 10.0
BARRIER_END = 0.15
ACCUMULATIONS = ("gather", "atomic", "colouring")
# What the rotations' iterations are taken to, per precision: ‖XᵀX − I‖ (Newton–Schulz) or the
# scaled Newton iteration's error, at the iterate they return; at round-off.
ROTATION_TOLERANCE = {"f64": 1e-16, "f32": 1e-7}


def vertex_incidence(tets: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR index vertex -> (4 e + corner) of its incident element corners, sorted by element."""
    corners = np.arange(tets.size, dtype=np.int32)
    vertex = tets.reshape(-1)
    order = np.argsort(vertex, kind="stable")
    offsets = np.zeros(n_points + 1, dtype=np.int32)
    np.cumsum(np.bincount(vertex, minlength=n_points), out=offsets[1:])
    return offsets, corners[order]


def colour_elements(tets: np.ndarray, n_points: int) -> list[np.ndarray]:
    """Greedy colouring: elements of one colour share no node (so need no atomics)."""
    offsets, corner_ids = vertex_incidence(tets, n_points)
    colour = np.full(len(tets), -1, dtype=np.int64)
    node_colours = [set() for _ in range(n_points)]
    for e, nodes in enumerate(tets):
        used = set().union(*(node_colours[v] for v in nodes))
        c = 0
        while c in used:
            c += 1
        colour[e] = c
        for v in nodes:
            node_colours[v].add(c)
    return [np.flatnonzero(colour == c).astype(np.int32) for c in range(colour.max() + 1)]


@ti.func
def edge_frame(a, b, c):
    """Orthonormal frame (columns) of a triangle: x along ab, z normal, as SOFA's "large"."""
    ex = (b - a).normalized()
    ez = ex.cross(c - a).normalized()
    ey = ez.cross(ex)
    return ti.Matrix.cols([ex, ey, ez])


@ti.func
def symmetric_eigen(A):
    """Eigenvalues (a vector) and orthonormal eigenvectors (columns) of a symmetric 3×3 matrix by
    cyclic Jacobi rotations: square roots only, to round-off in a few sweeps. Each rotation zeroes
    the (0, 1) entry, updating only the entries it changes (Numerical Recipes' `jacobi`), then
    relabels the axes cyclically (new a = old a + 1): one rotation's code, in a runtime loop, visits
    the pairs (0, 1), (1, 2), (2, 0) in turn and is back in the original labels after every third.
    This is inlined in many kernels; unrolled over the three pairs, with each rotation as full 3×3
    products, it was 5× the code."""
    D, V = A, ti.Matrix.identity(float, 3)
    for rotation in range(3 * 12):
        if rotation % 3 == 0:
            off = D[0, 1] ** 2 + D[0, 2] ** 2 + D[1, 2] ** 2
            if off <= 1e-32 * D.norm_sqr():
                break
        if D[0, 1] != 0.0:
            theta = (D[1, 1] - D[0, 0]) / (2.0 * D[0, 1])
            t = 1.0 / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / ti.sqrt(t * t + 1.0)
            s = t * c
            D[0, 0] -= t * D[0, 1]
            D[1, 1] += t * D[0, 1]
            D[0, 1], D[1, 0] = 0.0, 0.0
            d20, d21 = c * D[2, 0] - s * D[2, 1], s * D[2, 0] + c * D[2, 1]
            D[2, 0], D[0, 2], D[2, 1], D[1, 2] = d20, d20, d21, d21
            for i in ti.static(range(3)):
                v0, v1 = c * V[i, 0] - s * V[i, 1], s * V[i, 0] + c * V[i, 1]
                V[i, 0], V[i, 1] = v0, v1
        D = ti.Matrix([[D[1, 1], D[1, 2], D[1, 0]], [D[2, 1], D[2, 2], D[2, 0]], [D[0, 1], D[0, 2], D[0, 0]]])
        V = ti.Matrix.cols([ti.Vector([V[0, 1], V[1, 1], V[2, 1]]), ti.Vector([V[0, 2], V[1, 2], V[2, 2]]),
                            ti.Vector([V[0, 0], V[1, 0], V[2, 0]])])
    return ti.Vector([D[0, 0], D[1, 1], D[2, 2]]), V


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
def limit_tangent_stress(m: ti.template(), w: ti.template(), e, G):
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


@ti.func
def polar_rotation(F, tol):
    """Rotation of the polar decomposition F = R S by Higham's scaled Newton iteration.

    The scaling ζ = sqrt(‖X⁻¹‖/‖X‖) (Frobenius) needs only a square root, which every backend has
    in float64 (Vulkan's GLSL has no 64-bit pow, exp or trigonometry). An inverted element
    (det F < 0) gets the closest proper rotation: the orthogonal factor is reflected along the
    eigenvector of S with the smallest eigenvalue (Irving et al. 2004), found by Jacobi rotations
    (exact to round-off however close the eigenvalues; inverse iteration converged too slowly for
    an element mirrored whole, whose stretches are all near 1).

    Near orthogonality (a tissue's elements under moderate strain) Newton–Schulz gets there first,
    by products alone (`newton_schulz`; the scaled iteration's inverse, norms and square roots
    wait on one another): the same factor to round-off.
    """
    X, done = newton_schulz(F, tol)
    for _ in range(30):
        if done:
            break
        Xinv_t = X.inverse().transpose()
        zeta = ti.sqrt(Xinv_t.norm() / X.norm())
        Y = 0.5 * (zeta * X + Xinv_t / zeta)
        change = (Y - X).norm()
        X = Y
        done = change * change <= tol     # Y's error is about half the square of X's, `change`
    if F.determinant() < 0:
        S = X.transpose() @ F
        values, V = symmetric_eigen(0.5 * (S + S.transpose()))
        # The column of the smallest eigenvalue, chosen among static indices: a runtime index
        # into a local matrix breaks the SPIR-V (Vulkan) compile.
        smallest, v = values[0], ti.Vector([V[0, 0], V[1, 0], V[2, 0]])
        for i in ti.static(range(1, 3)):
            if values[i] < smallest:
                smallest, v = values[i], ti.Vector([V[0, i], V[1, i], V[2, i]])
        X = X @ (ti.Matrix.identity(float, 3) - 2.0 * v.outer_product(v))
    return X


@ti.func
def nodal_rotation(Re: ti.template(), valence: ti.template(), incidence: ti.template(), v, tol):
    """The orthonormalised average of the rotations of the elements around node v: the rotation
    of the polar decomposition of their mean X₀. Newton–Schulz, X ← X (3I - XᵀX) / 2, converges
    to it quadratically when the rotations are alike (X₀ nearly orthogonal: a few 3×3 products);
    otherwise (rotations far apart, or det X₀ ≤ 0) the scaled Newton iteration of the FEM. Where
    the rotations cancel in the mean (a half turned over against the other: X₀ singular, and its
    polar factor undefined) the node takes its first element's rotation; a node of no element the
    identity."""
    X = ti.Matrix.zero(float, 3, 3)
    for k in range(valence[v]):
        X += Re[incidence[v, k] // 4]
    S = X / ti.max(valence[v], 1)
    X = S
    done = False
    if ti.abs(S.determinant()) <= SINGULAR_MEAN:
        X = ti.Matrix.identity(float, 3)
        if valence[v] > 0:
            X = Re[incidence[v, 0] // 4]
        done = True
    elif S.determinant() > 0.0:
        X, done = newton_schulz(S, tol)
    if not done:
        X = polar_rotation(S, tol)
    return X


@ti.func
def newton_schulz(F, tol):
    """(X, converged): F's orthogonal polar factor by Newton–Schulz, X ← X (3I − XᵀX) / 2, which
    converges quadratically where F is nearly orthogonal (‖FᵀF − I‖ ≤ 0.5: stretches within about
    30 % of 1) by 3×3 products alone; farther away not converged, X = F. Converged once the last
    update left ‖XᵀX − I‖ within `tol`: it takes E = XᵀX − I to −¾E² + ¼E³, of norm at most ‖E‖²."""
    X, done = F, False
    for _ in range(12):
        E = X.transpose() @ X - ti.Matrix.identity(float, 3)
        e = E.norm()
        if e > 0.5:                             # too far from orthogonal for Newton–Schulz
            break
        X = X - 0.5 * (X @ E)
        if e * e <= tol:
            done = True
            break
    return X, done


# ---- per-element mathematics, over a model's argpack `m` (tissue.fem.model) and the FEM's work `w`


@ti.func
def deformation_gradient(m: ti.template(), e, x: ti.template()):
    t = m.tets[e]
    Ds = ti.Matrix.cols([x[t[1]] - x[t[0]], x[t[2]] - x[t[0]], x[t[3]] - x[t[0]]])
    return Ds @ m.Dm_inv[e]


@ti.func
def element_rotation(m: ti.template(), e, x: ti.template(), rotation: ti.template(), tol):
    R = ti.Matrix.identity(float, 3)
    if ti.static(rotation == "large"):
        t = m.tets[e]
        R = edge_frame(x[t[0]], x[t[1]], x[t[2]]) @ m.rest_frame[e].transpose()
    elif ti.static(rotation == "polar" or rotation == "invertible"):
        F = deformation_gradient(m, e, x)
        if ti.abs(F.determinant()) > FLAT_DETERMINANT:
            R = polar_rotation(F, tol)
        else:  # (nearly) flat element: the edge frame is still well defined
            t = m.tets[e]
            R = edge_frame(x[t[0]], x[t[1]], x[t[2]]) @ m.rest_frame[e].transpose()
    return R


@ti.func
def linear_stress(m: ti.template(), e, G):
    """σ of the symmetric part of the displacement gradient G (linear isotropic)."""
    lam, mu = m.elastic[e][1], m.elastic[e][2]
    eps = 0.5 * (G + G.transpose())
    return 2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(float, 3)


@ti.func
def nodal_forces(m: ti.template(), R, e, G):
    """Forces (columns 1..3; node 0 balances them) of the linear stress of the displacement
    gradient G, given in the element's rotated frame: f = -V R σ(sym G) ∇N."""
    return -m.elastic[e][0] * R @ linear_stress(m, e, G) @ m.Dm_inv[e].transpose()


@ti.func
def element_stress(m: ti.template(), e, R, F):
    """The rotated-frame stress of the element at F: linear in RᵀF − I, plus the compression
    limit's where it is active."""
    G = R.transpose() @ F - ti.Matrix.identity(float, 3)
    sigma = linear_stress(m, e, G)
    S = 0.5 * (G + G.transpose()) + ti.Matrix.identity(float, 3)
    if compressed(S):
        sigma += compression_stress(m, e, S)
    return sigma


@ti.func
def elastic_force(m: ti.template(), w: ti.template(), e, x: ti.template(), rotation: ti.template()):
    """-R Kₑ (Rᵀ x - X) on the element's nodes, as a 3×3 (nodes 1..3; node 0 = -sum), plus the
    compression limit's force where the last rotation update found it active."""
    R = w.R[e]
    F = deformation_gradient(m, e, x)
    H = nodal_forces(m, R, e, R.transpose() @ F - ti.Matrix.identity(float, 3))
    if ti.static(rotation == "invertible"):
        if w.limited[e].norm_sqr() > 0.0:
            H = -m.elastic[e][0] * R @ element_stress(m, e, R, F) @ m.Dm_inv[e].transpose()
    return H


@ti.func
def stiffness_product(m: ti.template(), w: ti.template(), e, p: ti.template(), rotation: ti.template()):
    """-R Kₑ Rᵀ p on the element's nodes (the tangent stiffness times p, with its sign), with the
    compression limit's tangent where it is active (so the step is implicit in it too)."""
    R = w.R[e]
    G = R.transpose() @ deformation_gradient(m, e, p)
    H = nodal_forces(m, R, e, G)
    if ti.static(rotation == "invertible"):
        H -= m.elastic[e][0] * R @ limit_tangent_stress(m, w, e, G) @ m.Dm_inv[e].transpose()
    return H


@ti.func
def diagonal_block(m: ti.template(), w: ti.template(), e, corner, rotation: ti.template()):
    """The element's 3×3 stiffness block R Kₐₐ Rᵀ of one corner (for block-Jacobi)."""
    Dt = m.Dm_inv[e].transpose()
    g = ti.Vector([0.0, 0.0, 0.0])
    if corner == 0:
        g = -(ti.Vector([Dt[0, 0], Dt[1, 0], Dt[2, 0]]) + ti.Vector([Dt[0, 1], Dt[1, 1], Dt[2, 1]])
              + ti.Vector([Dt[0, 2], Dt[1, 2], Dt[2, 2]]))
    else:
        g = ti.Vector([Dt[0, corner - 1], Dt[1, corner - 1], Dt[2, corner - 1]])
    V, lam, mu = m.elastic[e][0], m.elastic[e][1], m.elastic[e][2]
    K = V * ((lam + mu) * g.outer_product(g) + mu * g.dot(g) * ti.Matrix.identity(float, 3))
    if ti.static(rotation == "invertible"):
        D = w.limited[e]
        if D.norm_sqr() > 0.0:
            k = w.limit_curvature[e]
            for i in ti.static(range(3)):
                d = ti.Vector([D[0, i], D[1, i], D[2, i]])
                K += (V * k[i] * g.dot(d) ** 2) * d.outer_product(d)
    return w.R[e] @ K @ w.R[e].transpose()


# ---- loops (parallel when called at kernel top level) ----------------------------------------


@ti.func
def update_rotations(m: ti.template(), w: ti.template(), x: ti.template(), rotation: ti.template(), tol):
    """Element rotations at x, where the compression limit is active and its curvature there
    ("invertible"), and the
    count of inverted elements (det F ≤ 0): a caller should hear of them."""
    w.inverted[0] = 0
    for e in range(m.counts[1]):
        R = element_rotation(m, e, x, rotation, tol)
        w.R[e] = R
        D = ti.Matrix.zero(float, 3, 3)
        k = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(rotation == "invertible"):
            G = R.transpose() @ deformation_gradient(m, e, x)
            S = 0.5 * (G + G.transpose())
            if compressed(S):
                D, k = limited_directions(m, e, S)
        w.limited[e] = D
        w.limit_curvature[e] = k
        t = m.tets[e]
        if (x[t[1]] - x[t[0]]).dot((x[t[2]] - x[t[0]]).cross(x[t[3]] - x[t[0]])) <= 0:
            w.inverted[0] += 1


@ti.func
def _deposit(m: ti.template(), w: ti.template(), e, H, accumulation: ti.template()):
    """Hand the element's nodal vectors (H: nodes 1..3 as columns) to the accumulation."""
    t = m.tets[e]
    f0 = -(ti.Vector([H[0, 0], H[1, 0], H[2, 0]]) + ti.Vector([H[0, 1], H[1, 1], H[2, 1]])
           + ti.Vector([H[0, 2], H[1, 2], H[2, 2]]))
    if ti.static(accumulation == "gather"):
        w.buffer[4 * e] = f0
        for a in ti.static(range(3)):
            w.buffer[4 * e + a + 1] = ti.Vector([H[0, a], H[1, a], H[2, a]])
    elif ti.static(accumulation == "atomic"):
        w.accumulator[t[0]] += f0
        for a in ti.static(range(3)):
            w.accumulator[t[a + 1]] += ti.Vector([H[0, a], H[1, a], H[2, a]])
    else:  # colouring: no two elements of a colour share a node, plain writes are safe
        w.accumulator[t[0]] = w.accumulator[t[0]] + f0
        for a in ti.static(range(3)):
            w.accumulator[t[a + 1]] = w.accumulator[t[a + 1]] + ti.Vector([H[0, a], H[1, a], H[2, a]])


@ti.func
def scatter_element(m: ti.template(), w: ti.template(), what: ti.template(), e, src: ti.template(),
                    accumulation: ti.template(), rotation: ti.template()):
    """One element's part of `what` ("force": elastic forces at positions src; "stiffness":
    tangent stiffness times src), handed to the accumulation."""
    H = ti.Matrix.zero(float, 3, 3)
    if ti.static(what == "force"):
        H = elastic_force(m, w, e, src, rotation)
    else:
        H = stiffness_product(m, w, e, src, rotation)
    _deposit(m, w, e, H, accumulation)


@ti.func
def scatter(m: ti.template(), w: ti.template(), what: ti.template(), src: ti.template(), accumulation: ti.template(),
            rotation: ti.template()):
    """Element stage of `what`; its nodal sums are then read with `gathered(v)`.
    Colouring is not fused here: it needs a launch per colour (see `scatter_launch`)."""
    ti.static_assert(accumulation != "colouring")
    for e in range(m.counts[1]):
        scatter_element(m, w, what, e, src, accumulation, rotation)


@ti.func
def gathered(m: ti.template(), w: ti.template(), v, accumulation: ti.template()):
    """The nodal sum of the last scatter at vertex v (read once: atomic/colouring reset it)."""
    s = ti.Vector([0.0, 0.0, 0.0])
    if ti.static(accumulation == "gather"):
        for k in range(m.valence[v]):
            s += w.buffer[m.incidence[v, k]]
    else:
        s = w.accumulator[v]
        w.accumulator[v] = ti.Vector([0.0, 0.0, 0.0])
    return s


@ti.func
def stiffness_diagonal(m: ti.template(), w: ti.template(), v, rotation: ti.template()):
    """Σ over incident elements of R Kₐₐ Rᵀ at vertex v."""
    K = ti.Matrix.zero(float, 3, 3)
    for k in range(m.valence[v]):
        c = m.incidence[v, k]
        K += diagonal_block(m, w, c // 4, c % 4, rotation)
    return K


# ---- standalone launches (tests, tools) ----------------------------------------------------------


@ti.kernel
def _rotations_kernel(m: MODEL, w: FEM_WORK, x: ti.types.ndarray(), rotation: ti.template(), tol: ti.f64):
    update_rotations(m, w, x, rotation, tol)


@ti.kernel
def _scatter_kernel(m: MODEL, w: FEM_WORK, what: ti.template(), src: ti.types.ndarray(), accumulation: ti.template(),
                    rotation: ti.template()):
    scatter(m, w, what, src, accumulation, rotation)


@ti.kernel
def _scatter_colour_kernel(m: MODEL, w: FEM_WORK, what: ti.template(), src: ti.types.ndarray(),
                           order: ti.types.ndarray(), begin: ti.i32, end: ti.i32, rotation: ti.template()):
    for i in range(begin, end):
        scatter_element(m, w, what, order[i], src, "colouring", rotation)


@ti.kernel
def _gather_kernel(m: MODEL, w: FEM_WORK, out: ti.types.ndarray(), accumulation: ti.template()):
    for v in range(m.counts[0]):
        out[v] = gathered(m, w, v, accumulation)


@ti.kernel
def _stress_kernel(m: MODEL, x: ti.types.ndarray(), out: ti.types.ndarray(), rotation: ti.template(), tol: ti.f64):
    for e in range(m.counts[1]):
        R = element_rotation(m, e, x, rotation, tol)
        F = deformation_gradient(m, e, x)
        sigma = linear_stress(m, e, R.transpose() @ F - ti.Matrix.identity(float, 3))
        if ti.static(rotation == "invertible"):
            sigma = element_stress(m, e, R, F)
        out[e] = R @ sigma @ R.transpose()


class CorotationalFEM:
    """The elastic part of one soft body: its model (`tissue.fem.model.BodyModel`), the choice of
    rotations and accumulation, and the per-step work they need (element rotations `R`, the gather
    buffer or the atomic accumulator, the inverted-element count).

    The Taichi functions of this module take `fem.model.pack` and `fem.work` and are called from
    the kernels of a solver (see `tissue.solver.ImplicitEuler`); the `*_numpy` methods launch them
    alone, for tests and tools.
    """

    def __init__(self, mesh: TetMesh | BodyModel, material: Material | None = None, rotation: str = "large",
                 accumulation: str = "gather"):
        if rotation not in ROTATIONS:
            raise TissueError(f"rotation: unknown method {rotation!r}; expected one of {ROTATIONS}")
        if accumulation not in ACCUMULATIONS:
            raise TissueError(f"accumulation: unknown method {accumulation!r}; expected one of {ACCUMULATIONS}")
        self.model = mesh if isinstance(mesh, BodyModel) else BodyModel(mesh, material)
        self.rotation, self.accumulation = rotation, accumulation
        # Writes of the element rotations R (the solver counts its steps' too): what was computed
        # from them (the multigrid's nodal rotations) holds while this count has not moved.
        self.rotation_writes = 0
        self.rotation_tolerance = ROTATION_TOLERANCE[backend.current().precision]
        self._version = None
        self._colouring = None       # (order, offsets) of the colouring ablation; edits drop it
        self.resize()
        self.model.subscribe(self)

    def topology_changed(self, edit) -> None:
        self._colouring = None

    def resize(self) -> bool:
        """Match the work arrays to the model's capacity; True when they were re-allocated."""
        model = self.model
        if self._version == model.version:
            return False
        real = backend.current().real
        vec3, mat3 = ti.types.vector(3, real), ti.types.matrix(3, 3, real)
        n, m = model.node_capacity, model.element_capacity
        self.R = ti.ndarray(mat3, m)      # every step recomputes the rotations before using them
        self.R.from_numpy(np.tile(np.eye(3, dtype=real_numpy()), (m, 1, 1)))
        self.rotation_writes += 1
        self.work_arrays = dict(R=self.R, limited=ti.ndarray(mat3, m), limit_curvature=ti.ndarray(vec3, m),
                                inverted=ti.ndarray(ti.i32, 1),
                                buffer=ti.ndarray(vec3, 4 * m if self.accumulation == "gather" else 1),
                                accumulator=ti.ndarray(vec3, n if self.accumulation != "gather" else 1))
        self.work = FEM_WORK(**self.work_arrays)
        self._io = [ti.ndarray(vec3, n) for _ in range(2)]
        self._stresses = ti.ndarray(mat3, m)     # element_stress_numpy's (kept: an allocation costs ~1 ms)
        self._version = model.version
        return True

    @property
    def mesh(self) -> TetMesh:
        return self.model.mesh()

    @property
    def material(self) -> Material:
        return self.model.material

    @property
    def n_nodes(self) -> int:
        return self.model.n_nodes

    @property
    def n_elements(self) -> int:
        return self.model.n_elements

    def rotations(self) -> np.ndarray:
        """The element rotations of the last update (elements, 3, 3)."""
        return self.R.to_numpy()[:self.n_elements].astype(np.float64)

    # ---- standalone launches ---------------------------------------------------------------------

    def _vectors(self, values: np.ndarray, slot: int = 0):
        """One of two nodal arrays kept for the standalone launches, filled with `values`."""
        self.resize()
        array = self._io[slot]
        padded = np.zeros((array.shape[0], 3), dtype=real_numpy())
        padded[:self.n_nodes] = values
        array.from_numpy(padded)
        return array

    def scatter_launch(self, what: str, src) -> None:
        """The element stage as its own launch(es): one per colour when colouring."""
        m = self.model.pack
        if self.accumulation == "colouring":
            order, offsets = self._colours()
            for c in range(len(offsets) - 1):
                _scatter_colour_kernel(m, self.work, what, src, order, offsets[c], offsets[c + 1], self.rotation)
        else:
            _scatter_kernel(m, self.work, what, src, self.accumulation, self.rotation)

    def _colours(self):
        if self._colouring is None:
            colours = colour_elements(self.model.tets, self.n_nodes)
            self.n_colours = len(colours)
            order = ti.ndarray(ti.i32, self.n_elements)
            order.from_numpy(np.concatenate(colours))
            self._colouring = (order, [0] + [int(k) for k in np.cumsum([len(c) for c in colours])])
        return self._colouring

    def rotations_numpy(self, positions: np.ndarray) -> np.ndarray:
        """Element rotations (m, 3, 3) at the given positions (also stored for later products)."""
        self.rotation_writes += 1
        _rotations_kernel(self.model.pack, self.work, self._vectors(positions), self.rotation, self.rotation_tolerance)
        return self.rotations()

    def _gathered_numpy(self) -> np.ndarray:
        out = self._vectors(np.zeros((self.n_nodes, 3)), slot=1)
        _gather_kernel(self.model.pack, self.work, out, self.accumulation)
        return out.to_numpy()[:self.n_nodes]

    def elastic_forces_numpy(self, positions: np.ndarray, update_rotations: bool = True) -> np.ndarray:
        """Elastic nodal forces (n, 3) at the given positions."""
        x = self._vectors(positions)
        if update_rotations:
            self.rotation_writes += 1
            _rotations_kernel(self.model.pack, self.work, x, self.rotation, self.rotation_tolerance)
        self.scatter_launch("force", x)
        return self._gathered_numpy()

    def stiffness_product_numpy(self, vectors: np.ndarray) -> np.ndarray:
        """(-Σ R Kₑ Rᵀ) p with the current rotations."""
        self.scatter_launch("stiffness", self._vectors(vectors))
        return self._gathered_numpy()

    def element_stress_numpy(self, positions) -> np.ndarray:
        """Co-rotational stress R σ Rᵀ of each element (m, 3, 3) at the given positions: an (n, 3)
        array, or a nodal ndarray such as a solver's `x` (read in place)."""
        x = self._vectors(positions) if isinstance(positions, np.ndarray) else positions
        self.resize()
        out = self._stresses
        _stress_kernel(self.model.pack, x, out, self.rotation, self.rotation_tolerance)
        return out.to_numpy()[:self.n_elements].astype(np.float64)
