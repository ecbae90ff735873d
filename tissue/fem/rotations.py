"""Rotations of 3×3 matrices, as Taichi functions for the kernels: an edge frame ("large"), the
polar factor (scaled Newton, with Newton–Schulz near orthogonality; the closest proper rotation of
an inverted F), the orthonormalised mean of a node's element rotations, and the symmetric
eigen-decomposition these and the compression limit use. Square roots and products only: every
backend has them in float64.
"""

import taichi as ti

# The mean of a node's element rotations is taken as singular (no polar factor) below this
# determinant (1 for alike rotations; 0 when, e.g., I and a half turn average).
SINGULAR_MEAN = 1e-6
# What the rotations' iterations are taken to, per precision: ‖XᵀX − I‖ (Newton–Schulz) or the
# scaled Newton iteration's error, at the iterate they return; at round-off.
ROTATION_TOLERANCE = {"f64": 1e-16, "f32": 1e-7}


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
