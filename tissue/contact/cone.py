"""One contact's cone: the projection on K_mu, the natural-map error (numpy, and per contact in
Taichi), and the exact solution of one contact's 3×3 problem with the others fixed: the pieces
every solver of tissue.contact.frictional_contact (and the haptic loop) is made of. The problem
and the error measure are stated in that module's docstring.
"""

import numpy as np
import taichi as ti


def project_cone(x: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Projection of each row (x_n, x_t1, x_t2) of x (n, 3) on K_mu (closed form)."""
    xn, nt = x[:, 0], np.sqrt(x[:, 1] * x[:, 1] + x[:, 2] * x[:, 2])     # (np.linalg.norm's sum, fewer calls)
    # xn >= 0 matters when mu = 0 and nt = 0: a point on the negative normal axis is not in K_0.
    inside, polar = (nt <= mu * xn) & (xn >= 0), mu * nt <= -xn
    if inside.all():                # (zeros; a warm start whose contacts all stick inside)
        return x.copy()
    a = (xn + mu * nt) / (1.0 + mu * mu)
    scale = np.divide(mu * a, nt, out=np.zeros(a.shape, a.dtype), where=nt > 0)
    p = np.empty(x.shape, np.result_type(a, x))
    p[:, 0] = a
    np.multiply(scale[:, None], x[:, 1:], out=p[:, 1:])
    np.copyto(p, 0.0, where=polar[:, None])          # (masked copies: boolean indexing costs more)
    np.copyto(p, x, where=inside[:, None])
    return p


def natural_map_residual(W, q, mu, r) -> float:
    """||r - P_K(r - û)|| / (1 + ||q||) with u = W r + q (see the module docstring)."""
    q, r = np.asarray(q, dtype=np.float64), np.asarray(r, dtype=np.float64)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (len(q) // 3,))
    return float(np.sqrt(natural_map_error2(r, W @ r + q, mu)) / (1.0 + np.linalg.norm(q)))


def natural_map_error2(r, u, mu) -> float:
    """The squared natural-map error Σ |r - P_K(r - û)|² of reactions r at velocities u."""
    R, U = r.reshape(-1, 3), u.reshape(-1, 3)
    x = R - U
    x[:, 0] -= mu * np.sqrt(U[:, 1] * U[:, 1] + U[:, 2] * U[:, 2])     # (np.linalg.norm's sum, fewer calls)
    d = R - project_cone(x, mu)
    return float(np.sum(d * d))


# ----------------------------------------------------------------------------------------------
# Taichi functions: the local 3x3 problem and the per-contact error
# ----------------------------------------------------------------------------------------------

@ti.func
def _solve2(S, beta, c):
    """(S + beta I)^-1 c for a 2x2 S."""
    a, b, d, e = S[0, 0] + beta, S[0, 1], S[1, 0], S[1, 1] + beta
    det = a * e - b * d
    return ti.Vector([e * c[0] - b * c[1], a * c[1] - d * c[0]]) / det


@ti.func
def _slide_eval(S, c, ant, ann, bn, mu, beta):
    """F(beta) = 1 - mu r_n / |r_t| and its derivative, where r_t = (S + beta I)^-1 c and r_n
    follows from u_n = 0. A root is a sliding solution with u_t = -beta r_t."""
    rt = _solve2(S, beta, c)
    drt = -_solve2(S, beta, rt)
    nt = rt.norm()
    rn = -(bn + ant.dot(rt)) / ann
    drn = -ant.dot(drt) / ann
    dnt = rt.dot(drt) / nt
    return ti.Vector([1.0 - mu * rn / nt, -mu * (drn * nt - rn * dnt) / (nt * nt)])


@ti.func
def local_solve(A, b, mu):
    """Exact solution r of one contact's problem u = A r + b (A the 3x3 diagonal block of W).

    Separation iff b_n >= 0 (then r = 0 gives û_n = b_n >= 0; testing b_n rather than the sign of
    the sticking r_n stays right when A couples normal and tangent). Otherwise eliminate r_n with
    u_n = 0 (S: Schur complement of A_nn, c: right-hand side), giving r_t(beta) = (S + beta I)^-1 c
    where u_t = -beta r_t: beta = 0 is sticking, beta > 0 sliding with beta fixed by |r_t| = mu r_n.
    F(0) > 0 whenever the sticking reaction leaves the cone and F -> -inf as beta grows, so a
    bracketed, safeguarded Newton always finds a root. For isotropic diagonal A, F is linear in
    beta and the first Newton step is exact.
    """
    r = ti.Vector([0.0, 0.0, 0.0])
    if b[0] < 0.0:
        if mu <= 0.0:
            r[0] = -b[0] / A[0, 0]
        else:
            ann = A[0, 0]
            ant = ti.Vector([A[0, 1], A[0, 2]])
            atn = ti.Vector([A[1, 0], A[2, 0]])
            S = ti.Matrix([[A[1, 1], A[1, 2]], [A[2, 1], A[2, 2]]]) - atn.outer_product(ant) / ann
            c = atn * (b[0] / ann) - ti.Vector([b[1], b[2]])
            rt = _solve2(S, 0.0, c)
            rn = -(b[0] + ant.dot(rt)) / ann
            if rn < 0.0 or rt.norm() > mu * rn:     # sticking reaction outside the cone: slide
                lo, hi = 0.0, S[0, 0] + S[1, 1]
                for _ in range(200):                # grow hi until F(hi) < 0
                    if _slide_eval(S, c, ant, ann, b[0], mu, hi)[0] < 0.0:
                        break
                    lo = hi
                    hi *= 4.0
                beta = lo
                for _ in range(100):
                    f = _slide_eval(S, c, ant, ann, b[0], mu, beta)
                    if f[0] > 0.0:
                        lo = beta
                    else:
                        hi = beta
                    if ti.abs(f[0]) <= 1e-14 or hi - lo <= 1e-15 * hi:
                        break
                    step = beta - f[0] / f[1]
                    if not (lo < step < hi):        # Newton left the bracket: bisect
                        step = 0.5 * (lo + hi)
                    beta = step
                rt = _solve2(S, beta, c)
                rn = ti.max(-(b[0] + ant.dot(rt)) / ann, 0.0)
                rt *= mu * rn / rt.norm()           # land exactly on the cone's boundary
            r = ti.Vector([rn, rt[0], rt[1]])
    return r


@ti.func
def contact_error2(r, u, mu):
    """Squared natural-map error of one contact: |r - P_K(r - û)|^2."""
    x = r - u
    x[0] -= mu * ti.Vector([u[1], u[2]]).norm()
    e = r - project_contact(x, mu)
    return e.dot(e)


@ti.func
def vector_at(a: ti.template(), i):
    """Contact i's three entries of a flat array (3 per contact) as a vector."""
    return ti.Vector([a[3 * i], a[3 * i + 1], a[3 * i + 2]])


@ti.func
def matrix_at(blocks: ti.template(), i):
    """Block i of an array of 3×3 blocks (n, 3, 3) as a matrix."""
    A = ti.Matrix.zero(float, 3, 3)
    for a, c in ti.static(ti.ndrange(3, 3)):
        A[a, c] = blocks[i, a, c]
    return A


@ti.func
def project_contact(x, mu):
    """Projection of x = (x_n, x_t1, x_t2) on K_mu (as project_cone)."""
    xn, nt = x[0], ti.Vector([x[1], x[2]]).norm()
    p = x
    if mu * nt <= -xn:                              # polar cone (and x_n < 0 with mu = 0)
        p = ti.Vector([0.0, 0.0, 0.0])
    elif not (nt <= mu * xn and xn >= 0.0):
        a = (xn + mu * nt) / (1.0 + mu * mu)
        p = ti.Vector([a, mu * a * x[1] / nt, mu * a * x[2] / nt])
    return p

