"""The discrete 3-D frictional contact problem (FCLib form): projected block Gauss-Seidel, and the
dispatch to the other methods (`solve_frictional_contact`, `FrictionalContactSolver`).

Problem (Acary et al., FCLib): n contacts, per contact the order (normal, tangent1, tangent2);
given the Delassus matrix W (3n x 3n), the free velocity q (3n,) and friction coefficients mu (n,),
find reactions r with u = W r + q such that, for each contact,

    K_mu ∋ r ⊥ û ∈ K_mu*,   û = (u_n + mu |u_t|, u_t),   K_mu = {r_n >= 0, |r_t| <= mu r_n}

(De Saxcé's modified velocity; K_mu* = {mu |v_t| <= v_n} is the dual cone). Its three cases are
separation (r = 0, u_n >= 0), sticking (u = 0, r inside K_mu) and sliding (u_n = 0,
r_t = -mu r_n u_t / |u_t|). With mu = 0 it is the LCP 0 <= u_n ⊥ r_n >= 0, r_t = 0.

Error measure (used to stop and reported in `info.residual`): the natural map of FCLib / Siconos
`fc3d_compute_error` with rho = 1,

    residual = || r - P_{K_mu}(r - û) ||_2 / (1 + ||q||_2),

the norm over all 3n components; it is zero exactly at a solution. (Siconos divides by ||q||;
the 1 + keeps it defined for q = 0.)

Methods:
  * "auto" (the contact stage's default): Gauss-Seidel below over the whole problem while it
    makes progress (every AUTO_PHASE sweeps at least halve the residual, at a rate that reaches
    the tolerance within AUTO_SWEEPS, one launch), then "newton" from where it stopped. Warm-started problems of a few hundred rows mostly end within the
    sweeps, at microseconds each; the rest (many strongly coupled contacts, often more rows than
    the dofs they move: the press plate's 2,382-3,465 rows, where a sweep gains ~1 % of the
    residual) end in a few Newton steps (bench/contact_solvers.py).
  * "newton": semi-smooth Newton on the Alart–Curnier function (tissue.contact.newton), on the
    host (dense LU among the closing contacts), Gauss-Seidel sweeps its fallback.
  * "gauss_seidel" (the API's default; Jean & Moreau, Duriez et al. 2006): contacts swept in order, each
    contact's 3x3 problem solved exactly with the others' reactions fixed (see `_local_solve`).
    The sweep is sequential by nature, so the whole iteration loop runs serially inside ONE Taichi
    kernel (a launch costs more than a sweep of a few hundred contacts). A sweep reads W once
    (contact i gathers rows 3i..3i+2 of W times r); the exact residual needs u = W r + q, a second
    pass, so it is computed only when the errors met during the sweep say "converged" (plus at the
    start, which lets a warm start that already solves the problem cost 0 sweeps). Between two
    residual checks a sweep passes over the contacts that carry nothing and were apart (u_n > 0)
    when last solved, but for every REVISIT_EVERY-th sweep: the check sees them all again, so the
    stopping rule is unchanged, and most contacts within an alarm distance never touch (the
    pressed liver: ~140 of ~155). Hence also `reduce`: while at most half the contacts are in
    play (pushed or touching), the sweeps run on W among those alone, formed densely
    (FrictionalContactSolver._gauss_seidel); it pays on problems that need many sweeps.
    Anderson acceleration (`anderson` > 0, default ANDERSON_WINDOW): a sweep is a fixed-point map
    r <- G(r); after each sweep the next start is the combination of the last `anderson` + 1 sweeps'
    results whose residuals G(r) - r combine to the least norm (type II, Walker & Ni 2011),
    projected on the cones. A combined start whose sweep error exceeds the previous start's is
    rejected (back to the plain sweep's result, history cleared), at most ANDERSON_RESTARTS times,
    then plain sweeps; the stopping test is unchanged (the exact residual). On the contact stage's
    strongly coupled soft-body problems it cuts the sweeps to a tolerance 2-4x (bench/contact.py).
  * "jacobi": every contact solved in parallel from the previous iterate, then relaxed,
    r <- r + omega (r_local - r). Parallel (for GPUs and thousands of contacts) but it converges
    markedly slower than Gauss-Seidel on coupled problems (5-10x more iterations on the tests'
    problems). omega starts at min(1, 1/lambda_max(D^-1 W)) (D the 3x3 diagonal blocks; for the LCP
    relaxed block Jacobi converges when omega < 2/lambda_max). Safeguard: the residual is read
    every JACOBI_CHECK_EVERY iterations; when it exceeds twice the best seen, or the best has not
    improved for JACOBI_STALL_CHECKS checks, the best iterate is restored and omega halved.

W is held on the device dense (row-major), as 3x3 blocks in block-CSR (a large sparse W), or as
its factors W = scale Σ P Q Pᵀ (`FactoredDelassus`, the form compliance warping gives: the contact
stage never forms W, and a sweep reads the bodies' compliances on the touched nodes instead).
Taichi ndarrays are used rather than fields so that problems of any size reuse the same
compiled kernels and are freed with the solver; on the CPU plain numpy arrays take their place
(kernels read and write them in place), since allocating and filling a Taichi ndarray costs
about a millisecond, more than a whole solve of a hundred contacts. Reactions are accumulated in the backend's float
type (with float32, tolerances much below 1e-6 are out of reach).
"""


import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import taichi as ti

from .. import backend
from ..errors import TissueError
from . import newton
from .delassus import FactoredDelassus

METHODS = ("gauss_seidel", "jacobi", "newton", "auto")
LAYOUTS = ("auto", "dense", "csr")
# A sparse W goes to block-CSR when it has at least this many rows and at most this fill.
CSR_MIN_ROWS, CSR_MAX_FILL = 600, 0.2
ANDERSON_WINDOW = 5       # Gauss-Seidel's Anderson acceleration: sweeps combined (0: plain sweeps)
ANDERSON_RESTARTS = 10    # ... rejecting a combination that starts worse than the sweep before, at most this often
JACOBI_CHECK_EVERY = 10   # Jacobi reads its residual back (a device sync) every this many iterations
JACOBI_STALL_CHECKS = 20  # ... and halves omega after this many checks without a new best residual
REDUCE_FRACTION = 0.5     # reduce: Gauss-Seidel on the contacts in play while they are at most this fraction
AUTO_PHASE, AUTO_SWEEPS = 16, 64  # auto: Gauss-Seidel while each AUTO_PHASE sweeps halve the residual, at
                                  # a rate that reaches the tolerance within AUTO_SWEEPS, then Newton
REVISIT_EVERY = 8         # Gauss-Seidel: every this many sweeps, one that visits the contacts apart too


@dataclass
class ContactInfo:
    iterations: int      # sweeps (Gauss-Seidel) or parallel iterations (Jacobi) performed
    residual: float      # natural-map residual of the returned r (see module docstring)
    time_s: float        # wall time of solve() until r is back on the host (device synced); counts
                         # uploading q and r0 (and compiling, on a process's first call), not W's upload
    converged: bool      # residual <= tol
    method: str = "gauss_seidel"


# ----------------------------------------------------------------------------------------------
# numpy reference pieces: the cone projection and the natural-map residual
# ----------------------------------------------------------------------------------------------

def project_cone(x: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Projection of each row (x_n, x_t1, x_t2) of x (n, 3) on K_mu (closed form)."""
    xn, nt = x[:, 0], np.linalg.norm(x[:, 1:], axis=1)
    # xn >= 0 matters when mu = 0 and nt = 0: a point on the negative normal axis is not in K_0.
    inside, polar = (nt <= mu * xn) & (xn >= 0), mu * nt <= -xn
    a = (xn + mu * nt) / (1.0 + mu * mu)
    scale = np.divide(mu * a, nt, out=np.zeros_like(a), where=nt > 0)
    p = np.column_stack([a, scale[:, None] * x[:, 1:]])
    p[polar] = 0.0
    p[inside] = x[inside]
    return p


def natural_map_residual(W, q, mu, r) -> float:
    """||r - P_K(r - û)|| / (1 + ||q||) with u = W r + q (see the module docstring)."""
    q, r = np.asarray(q, dtype=np.float64), np.asarray(r, dtype=np.float64)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (len(q) // 3,))
    return float(np.sqrt(_error2_numpy(r, W @ r + q, mu)) / (1.0 + np.linalg.norm(q)))


def _error2_numpy(r, u, mu) -> float:
    """The squared natural-map error Σ |r - P_K(r - û)|² of reactions r at velocities u."""
    R, U = r.reshape(-1, 3), u.reshape(-1, 3)
    x = R - U
    x[:, 0] -= mu * np.linalg.norm(U[:, 1:], axis=1)
    return float(np.sum((R - project_cone(x, mu)) ** 2))


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
def _local_solve(A, b, mu):
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
def _contact_error2(r, u, mu):
    """Squared natural-map error of one contact: |r - P_K(r - û)|^2."""
    x = r - u
    ut = ti.Vector([u[1], u[2]]).norm()
    x[0] -= mu * ut
    xn, nt = x[0], ti.Vector([x[1], x[2]]).norm()
    p = ti.Vector([0.0, 0.0, 0.0])
    if nt <= mu * xn and xn >= 0.0:                # (xn >= 0: for mu = 0, nt = 0)
        p = x
    elif mu * nt > -xn:                             # neither inside K nor in its polar cone
        a = (xn + mu * nt) / (1.0 + mu * mu)
        p = ti.Vector([a, mu * a * x[1] / nt, mu * a * x[2] / nt])
    e = r - p
    return e.dot(e)


@ti.func
def _vec(a: ti.template(), i):
    return ti.Vector([a[3 * i], a[3 * i + 1], a[3 * i + 2]])


@ti.func
def _block(Wd: ti.template(), i):
    A = ti.Matrix.zero(float, 3, 3)
    for a, c in ti.static(ti.ndrange(3, 3)):
        A[a, c] = Wd[i, a, c]
    return A


@ti.func
def _error2(r: ti.template(), u: ti.template(), mu: ti.template()):
    s = 0.0
    for i in range(mu.shape[0]):
        s += _contact_error2(_vec(r, i), _vec(u, i), mu[i])
    return s


# ----------------------------------------------------------------------------------------------
# Products with W, by layout. Every kernel takes the layout's arrays in three slots a, b, c:
#   DENSE     a = W (3n × 3n)
#   CSR       a = indptr, b = indices, c = blocks (3×3 block (i, indices[k]) of W in blocks[k])
#   FACTORED  a = index, b = blocks, c = Q (FactoredDelassus.packed()); y = scale Q Pᵀ r, z = Pᵀ r
# Dense and block-CSR gather row i of W times r (no atomics; sums in registers). The factored
# layout keeps y up to date instead: (W r)_i = P_i y, and a change Δr_i adds scale Q P_iᵀ Δr_i
# to y (three rows of Q per block of P_i, read in memory order).
# ----------------------------------------------------------------------------------------------

DENSE, CSR, FACTORED = 0, 1, 2


@ti.func
def _wr_dense(W: ti.template(), r: ti.template(), i):
    s0, s1, s2 = 0.0, 0.0, 0.0
    for l in range(r.shape[0]):
        rl = r[l]
        s0 += W[3 * i, l] * rl
        s1 += W[3 * i + 1, l] * rl
        s2 += W[3 * i + 2, l] * rl
    return ti.Vector([s0, s1, s2])


@ti.func
def _wr_csr(indptr: ti.template(), indices: ti.template(), blocks: ti.template(), r: ti.template(), i):
    s = ti.Vector([0.0, 0.0, 0.0])
    for k in range(indptr[i], indptr[i + 1]):
        j = indices[k]
        for a, c in ti.static(ti.ndrange(3, 3)):
            s[a] += blocks[k, a, c] * r[3 * j + c]
    return s


@ti.func
def _factored_offsets(index: ti.template(), n, nnz):
    """Offsets of ptr, col, segment, y_offset, q_offset in FactoredDelassus.packed()."""
    o_col = n + 1
    o_seg = o_col + nnz
    o_y = o_seg + nnz
    segments = (index.shape[0] - o_y - 1) // 2
    return o_col, o_seg, o_y, o_y + segments + 1, segments


@ti.func
def _wr_factored(index: ti.template(), blocks: ti.template(), y: ti.template(), n, i):
    o_col = n + 1
    s = ti.Vector([0.0, 0.0, 0.0])
    for e in range(index[i], index[i + 1]):
        c = index[o_col + e]
        s += _block(blocks, e) @ ti.Vector([y[c], y[c + 1], y[c + 2]])
    return s


@ti.func
def _wr(layout: ti.template(), a: ti.template(), b: ti.template(), c: ti.template(), y: ti.template(),
        r: ti.template(), i):
    """(W r)_i (for FACTORED: P_i y, with y up to date)."""
    s = ti.Vector([0.0, 0.0, 0.0])
    if ti.static(layout == DENSE):
        s = _wr_dense(a, r, i)
    elif ti.static(layout == CSR):
        s = _wr_csr(a, b, c, r, i)
    else:
        s = _wr_factored(a, b, y, r.shape[0] // 3, i)
    return s


@ti.func
def _spread(index: ti.template(), blocks: ti.template(), Q: ti.template(), y: ti.template(), n, i, dr, scale):
    """y += scale Q P_iᵀ dr: for each block of contact i, three rows of its segment's Q."""
    o_col, o_seg, o_y, o_q, _ = _factored_offsets(index, n, blocks.shape[0])
    for e in range(index[i], index[i + 1]):
        z = scale * (_block(blocks, e).transpose() @ dr)
        seg = index[o_seg + e]
        y0 = index[o_y + seg]
        d = index[o_y + seg + 1] - y0
        row = index[o_q + seg] + (index[o_col + e] - y0) * d
        for m in range(d):
            y[y0 + m] += Q[row + m] * z[0] + Q[row + d + m] * z[1] + Q[row + 2 * d + m] * z[2]


@ti.func
def _refresh(layout: ti.template(), a: ti.template(), b: ti.template(), c: ti.template(), r: ti.template(),
             y: ti.template(), z: ti.template(), scale):
    """FACTORED: y = scale Q Pᵀ r from scratch (z = Pᵀ r first, then one product per segment);
    after a change of r other than one contact's (a start, an Anderson step), and before the
    exact residual, so rounding in the running updates never accumulates into it."""
    if ti.static(layout == FACTORED):
        n = r.shape[0] // 3
        o_col, o_seg, o_y, o_q, segments = _factored_offsets(a, n, b.shape[0])
        for k in range(a[o_q - 1]):
            z[k] = 0.0
        for i in range(n):
            ri = _vec(r, i)
            for e in range(a[i], a[i + 1]):
                t = _block(b, e).transpose() @ ri
                col = a[o_col + e]
                for k in ti.static(range(3)):
                    z[col + k] += t[k]
        for k in range(a[o_q - 1]):
            y[k] = 0.0
        for seg in range(segments):
            # y += scale z_m Q[m, :] for each dof m with z_m ≠ 0 (Q symmetric: a row, in memory
            # order); most contacts carry no reaction, so most of z is zero.
            y0 = a[o_y + seg]
            d = a[o_y + seg + 1] - y0
            row = a[o_q + seg]
            for m in range(d):
                zm = scale * z[y0 + m]
                if zm != 0.0:
                    for k in range(d):
                        y[y0 + k] += c[row + m * d + k] * zm


@ti.func
def _residual(layout: ti.template(), a: ti.template(), b: ti.template(), c: ti.template(), q: ti.template(),
              mu: ti.template(), r: ti.template(), u: ti.template(), y: ti.template(), z: ti.template(), scale):
    """u = W r + q for every contact, and the squared natural-map error of r."""
    _refresh(layout, a, b, c, r, y, z, scale)
    for i in range(mu.shape[0]):
        ui = _vec(q, i) + _wr(layout, a, b, c, y, r, i)
        for k in ti.static(range(3)):
            u[3 * i + k] = ui[k]
    return _error2(r, u, mu)


@ti.func
def _project(x, mu):
    """Projection of x = (x_n, x_t1, x_t2) on K_mu (as project_cone)."""
    xn, nt = x[0], ti.Vector([x[1], x[2]]).norm()
    p = x
    if mu * nt <= -xn:                              # polar cone (and x_n < 0 with mu = 0)
        p = ti.Vector([0.0, 0.0, 0.0])
    elif not (nt <= mu * xn and xn >= 0.0):
        a = (xn + mu * nt) / (1.0 + mu * mu)
        p = ti.Vector([a, mu * a * x[1] / nt, mu * a * x[2] / nt])
    return p


@ti.func
def _save(r: ti.template(), hist: ti.template(), row, on):
    if on > 0:
        for l in range(r.shape[0]):
            hist[row, l] = r[l]


@ti.func
def _accelerate(r: ti.template(), hist: ti.template(), gram: ti.template(), mu: ti.template(), window, est, state):
    """After a sweep whose start had the running error `est`: state = (Anderson steps since the
    last restart, restarts left, the previous start's error). A combined start worse than the
    previous one is rejected: back to the previous sweep's result (what plain Gauss-Seidel had),
    history cleared; after `restarts` rejections, plain sweeps only."""
    since, on, last = ti.cast(state[0], ti.i32), ti.cast(state[1], ti.i32), state[2]
    if since > 1 and est > last:
        for l in range(r.shape[0]):
            r[l] = hist[2 * window, l]
        since, on = 0, on - 1
    else:
        last = est
        _anderson(r, hist, gram, mu, since, window)
        since += 1
    return ti.Vector([since, on, last])


@ti.func
def _anderson(r: ti.template(), hist: ti.template(), gram: ti.template(), mu: ti.template(), k, m):
    """Anderson step after sweep k (k = 0: the first since a restart). r holds g = G(x), the
    sweep's result, and hist[2m + 2] the x it started from. hist rows 0..m-1 hold ΔG, rows m..2m-1
    ΔF (ring buffers, F = G(x) - x), rows 2m, 2m + 1 the previous g and f; gram[i, j] = ΔF_i·ΔF_j.
    r <- P_K(g - ΔG γ) with γ = argmin |f - ΔF γ| (normal equations, Cholesky)."""
    n3 = r.shape[0]
    slot = (k - 1) % m
    xr, gp, fp = 2 * m + 2, 2 * m, 2 * m + 1
    for l in range(n3):
        g, f = r[l], r[l] - hist[xr, l]
        if k > 0:
            hist[slot, l] = g - hist[gp, l]
            hist[m + slot, l] = f - hist[fp, l]
        hist[gp, l], hist[fp, l] = g, f
    p = ti.min(k, m)
    if p > 0:
        for j in range(p):                          # the new column of the Gram matrix, and ΔFᵀ f
            a, b = 0.0, 0.0
            for l in range(n3):
                a += hist[m + slot, l] * hist[m + j, l]
                b += hist[m + j, l] * hist[fp, l]
            gram[slot, j], gram[j, slot], gram[j, m] = a, a, b
        # Cholesky of the p×p Gram matrix (regularised: its columns become nearly dependent) in
        # gram[.., m + 1 ..], then γ into gram[.., 2m + 1].
        trace = 0.0
        for j in range(p):
            trace += gram[j, j]
        ok = trace > 0.0
        c = m + 1
        for j in range(p):
            d = gram[j, j] + 1e-10 * trace
            for i in range(j):
                d -= gram[j, c + i] ** 2
            if d <= 0.0:
                ok = False
            d = ti.sqrt(ti.max(d, 1e-300))
            gram[j, c + j] = d
            for i in range(j + 1, p):
                e = gram[i, j]
                for t in range(j):
                    e -= gram[i, c + t] * gram[j, c + t]
                gram[i, c + j] = e / d
        if ok:
            y = 2 * m + 1
            for i in range(p):                      # forward: L z = ΔFᵀ f
                e = gram[i, m]
                for t in range(i):
                    e -= gram[i, c + t] * gram[t, y]
                gram[i, y] = e / gram[i, c + i]
            for i0 in range(p):                     # backward: Lᵀ γ = z
                i = p - 1 - i0
                e = gram[i, y]
                for t in range(i + 1, p):
                    e -= gram[t, c + i] * gram[t, y]
                gram[i, y] = e / gram[i, c + i]
            for i in range(mu.shape[0]):
                x = _vec(r, i)
                for j in range(p):
                    for a in ti.static(range(3)):
                        x[a] -= gram[j, y] * hist[j, 3 * i + a]
                x = _project(x, mu[i])
                for a in ti.static(range(3)):
                    r[3 * i + a] = x[a]


# ----------------------------------------------------------------------------------------------
# Gauss-Seidel: all sweeps in one launch, serial. The exact residual needs u = W r + q (one more
# pass over W), so it is computed only when the sweep's running estimate says "converged" (and at
# the start and the end); between two, u holds each contact's value when it was last solved.
# ----------------------------------------------------------------------------------------------

@ti.kernel
def _gauss_seidel(layout: ti.template(), a: ti.types.ndarray(), b: ti.types.ndarray(), c: ti.types.ndarray(),
                  Wd: ti.types.ndarray(), q: ti.types.ndarray(), mu: ti.types.ndarray(), r: ti.types.ndarray(),
                  u: ti.types.ndarray(), y: ti.types.ndarray(), z: ti.types.ndarray(), hist: ti.types.ndarray(),
                  gram: ti.types.ndarray(), window: ti.i32, restarts: ti.i32, max_it: ti.i32, tol2: float,
                  scale: float, revisit: ti.i32, stall: ti.i32, stats: ti.types.ndarray()):
    """Sweeps until the residual is ≤ tol2 (squared) or max_it sweeps; with stall > 0 also when
    `stall` sweeps did not halve the residual, or would not reach tol2 within max_it at the rate
    of the last `stall` (stats[2] = 1: stalled), read every `stall` sweeps."""
    it, est, err2, since, on, last = 0, 0.0, 0.0, 0, restarts if window > 0 else 0, 1e300
    phase_err2, stalled = 0.0, 0
    n = mu.shape[0]
    _refresh(layout, a, b, c, r, y, z, scale)
    while True:
        at_phase = stall > 0 and it % stall == 0
        if it == 0 or est <= tol2 or it >= max_it or at_phase:
            err2 = _residual(layout, a, b, c, q, mu, r, u, y, z, scale)
            if err2 <= tol2 or it >= max_it:
                break
            if at_phase:
                # Stalled: these sweeps did not halve the residual, or at their rate the cap
                # comes before the tolerance (then the sweeps to it are spent for nothing).
                if it > 0 and (err2 > 0.25 * phase_err2 or
                               err2 * ti.pow(err2 / phase_err2, (max_it - it) / stall) > tol2):
                    stalled = 1
                    break
                phase_err2 = err2
        _save(r, hist, 2 * window + 2, on)
        est = 0.0
        for i in range(n):
            # Contact i solved with the others fixed; est gathers the error the old r_i had (a
            # cheap running estimate of the residual). A contact that carries nothing and was
            # apart (u_n > 0) when last seen is passed over until the next residual check, which
            # sees every contact, or the next `revisit`-th sweep (neighbours' pushes can close its
            # gap meanwhile; without it, problems stopped by the sweep cap penetrated 4-7× deeper):
            # most of those within the alarm distance never touch.
            ri = _vec(r, i)
            if ri.norm_sqr() == 0.0 and u[3 * i] > 0.0 and it % revisit != revisit - 1:
                continue
            A = _block(Wd, i)
            ui = _vec(q, i) + _wr(layout, a, b, c, y, r, i)
            rnew = _local_solve(A, ui - A @ ri, mu[i])
            for k in ti.static(range(3)):
                r[3 * i + k] = rnew[k]
                u[3 * i + k] = ui[k]
            est += _contact_error2(ri, ui, mu[i])
            if ti.static(layout == FACTORED):
                dr = rnew - ri
                if dr.dot(dr) > 0.0:
                    _spread(a, b, c, y, n, i, dr, scale)
        it += 1
        if on > 0:
            acc = _accelerate(r, hist, gram, mu, window, est, ti.Vector([since, on, last]))
            since, on, last = ti.cast(acc[0], ti.i32), ti.cast(acc[1], ti.i32), acc[2]
            _refresh(layout, a, b, c, r, y, z, scale)
    stats[0] = it
    stats[1] = err2
    stats[2] = stalled


# ----------------------------------------------------------------------------------------------
# Jacobi kernels: one launch per stage, everything parallel
# ----------------------------------------------------------------------------------------------

@ti.kernel
def _matvec(layout: ti.template(), a: ti.types.ndarray(), b: ti.types.ndarray(), c: ti.types.ndarray(),
            q: ti.types.ndarray(), r: ti.types.ndarray(), u: ti.types.ndarray(), y: ti.types.ndarray(),
            z: ti.types.ndarray(), scale: float):
    """u = W r + q (FACTORED: y refreshed on one thread first, then every contact in parallel)."""
    for _ in range(1):
        _refresh(layout, a, b, c, r, y, z, scale)
    for i in range(q.shape[0] // 3):
        ui = _vec(q, i) + _wr(layout, a, b, c, y, r, i)
        for k in ti.static(range(3)):
            u[3 * i + k] = ui[k]


@ti.kernel
def _jacobi_step(Wd: ti.types.ndarray(), mu: ti.types.ndarray(), r: ti.types.ndarray(),
                 u: ti.types.ndarray(), omega: float):
    for i in range(mu.shape[0]):
        A = _block(Wd, i)
        ri = _vec(r, i)
        d = _local_solve(A, _vec(u, i) - A @ ri, mu[i]) - ri
        for c in ti.static(range(3)):               # a convex combination stays in the cone
            r[3 * i + c] += omega * d[c]


@ti.kernel
def _error2_kernel(r: ti.types.ndarray(), u: ti.types.ndarray(), mu: ti.types.ndarray(),
                   stats: ti.types.ndarray()):
    stats[1] = 0.0
    for i in range(mu.shape[0]):
        stats[1] += _contact_error2(_vec(r, i), _vec(u, i), mu[i])


# ----------------------------------------------------------------------------------------------
# Python side: validation, upload, solve loops
# ----------------------------------------------------------------------------------------------

def _finite(name, a):
    if not np.all(np.isfinite(a)):
        raise TissueError(f"{name}: contains non-finite entries (nan or inf)")


class _HostArray(np.ndarray):
    """A numpy array with the Taichi ndarray methods used here (CPU only: no copies)."""

    def from_numpy(self, a):
        self[...] = a

    def to_numpy(self):
        return np.array(self)

    def copy_from(self, other):
        self[...] = other


def _array(shape, dtype):
    """A zeroed kernel argument: numpy on the CPU, a Taichi ndarray elsewhere."""
    if backend.current().arch == "cpu":
        npt = np.int32 if dtype == ti.i32 else (np.float64 if dtype == ti.f64 else np.float32)
        return np.zeros(shape, dtype=npt).view(_HostArray)
    return ti.ndarray(dtype=dtype, shape=shape)


def _dofs(contacts):
    """The rows 3i, 3i + 1, 3i + 2 of each contact i."""
    return (3 * np.asarray(contacts)[:, None] + np.arange(3)).ravel()


def _diagonal_blocks(W, n):
    if sp.issparse(W):
        B = sp.bsr_matrix(W, blocksize=(3, 3))
        rows = np.repeat(np.arange(n), np.diff(B.indptr))
        on = B.indices == rows
        D = np.zeros((n, 3, 3))
        np.add.at(D, rows[on], B.data[on])
        return D
    idx = np.arange(n)
    return W.reshape(n, 3, n, 3)[idx, :, idx, :]


class FrictionalContactSolver:
    """W and mu validated and uploaded once; solve() may then run for many q (as the haptic loop
    re-solves with a new free velocity between two simulation steps)."""

    def __init__(self, W, mu, method: str = "gauss_seidel", layout: str = "auto", omega=None, check: bool = True,
                 anderson: int = ANDERSON_WINDOW, reduce: bool = False):
        """anderson: Gauss-Seidel's Anderson window (0: plain sweeps; see the module docstring).
        reduce: Gauss-Seidel sweeps the contacts in play alone, W among them formed (see `_gauss_seidel`;
        method 'gauss_seidel' only).
        check=False skips the finiteness and positive-definiteness checks of W (O(n²) and a
        3×3 eigenproblem per contact): for a caller that builds W itself (the contact stage)."""
        if method not in METHODS:
            raise TissueError(f"method: unknown value {method!r}; expected one of {', '.join(METHODS)}")
        if layout not in LAYOUTS:
            raise TissueError(f"layout: unknown value {layout!r}; expected one of {', '.join(LAYOUTS)}")
        if int(anderson) != anderson or anderson < 0:
            raise TissueError(f"anderson: must be a non-negative integer, got {anderson!r}")
        factored = isinstance(W, FactoredDelassus)
        if factored:
            if check:
                for name in ("blocks", "Q", "diagonal"):
                    _finite(f"W.{name}", getattr(W, name))
        elif sp.issparse(W):
            W = sp.csr_matrix(W, dtype=np.float64)
            _finite("W", W.data)
        else:
            W = np.asarray(W, dtype=np.float64)
            if W.ndim != 2:
                raise TissueError(f"W: must be a 2-D matrix, got shape {W.shape}")
            if check:
                _finite("W", W)
        if W.shape[0] != W.shape[1]:
            raise TissueError(f"W: must be square, got shape {W.shape}")
        if W.shape[0] % 3:
            raise TissueError(f"W: size must be 3 x (number of contacts), got {W.shape[0]}")
        n = W.shape[0] // 3
        mu = np.asarray(mu, dtype=np.float64)
        if mu.ndim == 0:
            mu = np.full(n, float(mu))
        if mu.shape != (n,):
            raise TissueError(f"mu: expected a scalar or shape ({n},) to match W {W.shape}, got {mu.shape}")
        _finite("mu", mu)
        if np.any(mu < 0):
            raise TissueError(f"mu: negative friction coefficient at contact {int(np.argmax(mu < 0))}")
        D = W.diagonal if factored else _diagonal_blocks(W, n)
        if n and check:
            sym = 0.5 * (D + D.transpose(0, 2, 1))
            lo = np.linalg.eigvalsh(sym)[:, 0]
            bad = np.flatnonzero(lo <= 1e-14 * np.abs(sym).max(axis=(1, 2)))
            if len(bad):
                raise TissueError(f"W: diagonal 3x3 block of contact {bad[0]} is not positive definite"
                                  f" (smallest eigenvalue {lo[bad[0]]:.3g}; {len(bad)} such block(s))")
        self.n, self.W, self.mu, self.method, self._D_host = n, W, mu, method, D
        self.anderson = int(anderson) if method != "jacobi" else 0
        self.reduce = bool(reduce) and method == "gauss_seidel"      # (auto sweeps the whole problem)
        dense = layout == "dense" or (layout == "auto" and (
            not sp.issparse(W) or W.shape[0] < CSR_MIN_ROWS or W.nnz > CSR_MAX_FILL * W.shape[0] ** 2))
        self.layout = FACTORED if factored else (DENSE if dense else CSR)
        # Jacobi's starting relaxation factor (given, or estimated from the spectrum of D^-1 W).
        self.omega = float(omega) if omega is not None else (
            self._initial_omega(D) if method == "jacobi" else 1.0)
        if n:
            self._upload(D)

    @property
    def dense(self) -> bool:
        """W held as a dense matrix on the device."""
        return self.layout == DENSE

    def _initial_omega(self, D):
        """min(1, 1/lambda_max(D^-1 W)) by a few power iterations (they approach from below)."""
        if self.n == 0:
            return 1.0
        Dinv = np.linalg.inv(D)
        x = np.random.default_rng(0).standard_normal(3 * self.n)
        lam = 1.0
        for _ in range(30):
            y = np.einsum("iab,ib->ia", Dinv, (self.W @ x).reshape(-1, 3)).ravel()
            lam = np.linalg.norm(y) / np.linalg.norm(x)
            x = y / np.linalg.norm(y)
        return min(1.0, 1.0 / lam)

    def _upload(self, D):
        real = backend.current().real
        npr = np.float64 if real == ti.f64 else np.float32

        def nd(a, dtype=real):
            a = np.ascontiguousarray(a, dtype=npr if dtype == real else np.int32)
            if backend.current().arch == "cpu":
                return a.view(_HostArray)
            arr = ti.ndarray(dtype=dtype, shape=a.shape)
            arr.from_numpy(a)
            return arr

        self._npr = npr
        m = 3 * self.n
        self._Wd, self._mu = nd(D), nd(self.mu)
        self._q, self._r, self._u = (_array((m,), real) for _ in range(3))
        self._stats = _array((3,), real)
        m = self.anderson                            # Anderson's history (see _anderson)
        self._hist = _array((2 * m + 3, 3 * self.n) if m else (1, 1), real)
        self._gram = _array((m, 2 * m + 2) if m else (1, 1), real)
        # The layout's arrays (slots a, b, c of the kernels, see "Products with W"), the factored
        # layout's y and z (one element elsewhere) and its scale.
        none = _array((1,), real)
        self._y = self._z = none
        self._scale = 1.0
        if self.layout == DENSE:
            W = self.W.toarray() if sp.issparse(self.W) else self.W
            self._abc = (nd(W), none, none)
        elif self.layout == CSR:
            B = sp.bsr_matrix(sp.csr_matrix(self.W), blocksize=(3, 3))   # csr_matrix drops zeros
            B.sort_indices()
            self._abc = (nd(B.indptr, ti.i32), nd(B.indices, ti.i32), nd(B.data))
        else:
            W = self.W
            self._abc = (nd(W.packed(), ti.i32), nd(W.blocks), nd(W.Q))
            self._y, self._z = (_array((max(1, int(W.y_offset[-1])),), real) for _ in range(2))
            self._scale = float(W.scale)

    def solve(self, q, tol: float = 1e-6, max_iterations: int = 1000, r0=None):
        n = self.n
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (3 * n,):
            raise TissueError(f"q: expected shape ({3 * n},) to match W {self.W.shape}, got {q.shape}")
        _finite("q", q)
        if r0 is None:
            r0 = np.zeros(3 * n)
        r0 = np.asarray(r0, dtype=np.float64)
        if r0.shape != (3 * n,):
            raise TissueError(f"r0: expected shape ({3 * n},) to match W {self.W.shape}, got {r0.shape}")
        _finite("r0", r0)
        if not (np.isfinite(tol) and tol > 0):
            raise TissueError(f"tol: must be a positive number, got {tol!r}")
        if int(max_iterations) != max_iterations or max_iterations < 0:
            raise TissueError(f"max_iterations: must be a non-negative integer, got {max_iterations!r}")
        max_iterations = int(max_iterations)
        if n == 0:
            self.u = np.zeros(0)
            return np.zeros(0), ContactInfo(0, 0.0, 0.0, True, self.method)

        t0 = time.perf_counter()
        self._q_host = q
        self._q.from_numpy(q.astype(self._npr))
        # Start inside the cones: Jacobi's relaxation keeps r where it starts.
        self._r.from_numpy(project_cone(r0.reshape(-1, 3), self.mu).ravel().astype(self._npr))
        tol_abs = tol * (1.0 + np.linalg.norm(q))
        run = {"gauss_seidel": self._gauss_seidel, "jacobi": self._jacobi, "newton": self._newton,
               "auto": self._auto}[self.method]
        iterations = run(max_iterations, tol_abs)
        backend.sync()
        r = self._r.to_numpy().astype(np.float64)
        elapsed = time.perf_counter() - t0
        if self.method != "jacobi" and self._npr == np.float64:
            # The kernel's own error and u of the returned r (the same formulas, in float64).
            residual = float(np.sqrt(self._last_error2)) / (1.0 + float(np.linalg.norm(q)))
            self.u = self._u.to_numpy()
        else:
            residual = natural_map_residual(self.W, q, self.mu, r)   # in float64, whatever the backend
            self.u = self.W @ r + q
        info = ContactInfo(iterations, residual, elapsed, residual <= tol, self.method)
        return r, info

    def _sweeps(self, max_iterations, tol_abs, stall: int = 0) -> int:
        """Gauss-Seidel sweeps over the whole problem from the current r, in one launch (0 sweeps:
        u and the residual of r alone); with `stall`, stopped early when that many sweeps did
        not halve the residual or, at their rate, would not reach tol_abs within max_iterations
        (self._stalled)."""
        _gauss_seidel(self.layout, *self._abc, self._Wd, self._q, self._mu, self._r, self._u, self._y, self._z,
                      self._hist, self._gram, self.anderson, ANDERSON_RESTARTS, max_iterations, tol_abs ** 2,
                      self._scale, REVISIT_EVERY, stall, self._stats)
        stats = self._stats.to_numpy()
        self._last_error2, self._stalled = float(stats[1]), bool(stats[2])
        return int(stats[0])

    def _gauss_seidel(self, max_iterations, tol_abs):
        """Without `reduce`: sweeps over the whole problem, in one launch. With it: sweeps on the
        contacts in play, those pushed (r ≠ 0) or touching (u_n ≤ 0). Within an alarm distance
        most contacts never touch (the pressed liver: ~15 of ~150), so W among the k in play is
        formed (3k × 3k, dense) and swept: a sweep there costs a few µs, against ~25 µs over the
        factors, whose updates run through every dof the contacts move, and Anderson's
        combinations see only the reactions that move. Forming W there and checking the whole
        problem (numpy: a launch with the kernel's arguments costs more) add about a
        millisecond, which pays on problems that need more than a few dozen sweeps (the liver
        pressed at 450 rows: 2.1 against 2.7 ms per solve, side by side in one run). After each
        solve on the contacts in play, the whole problem's residual adds those found
        penetrating; separated ones carry r = 0, their exact solution, so the stopping rule is
        the whole problem's. Sweeps (the iteration cap) count those of every solve. When more
        than REDUCE_FRACTION of the contacts are in play, or nothing new comes in, the remaining
        sweeps run on the whole problem."""
        if not self.reduce:
            return self._sweeps(max_iterations, tol_abs)
        q = self._q_host
        r = self._r.to_numpy().astype(np.float64)
        its, play = 0, np.zeros(self.n, bool)
        while True:
            u = self.W @ r + q
            error2 = _error2_numpy(r, u, self.mu)
            if error2 <= tol_abs ** 2 or its >= max_iterations:
                break
            new = ((r.reshape(-1, 3) != 0).any(axis=1) | (u[0::3] <= 0)) & ~play
            if not new.any() or np.count_nonzero(play | new) > REDUCE_FRACTION * self.n:
                self._r.from_numpy(r.astype(self._npr))
                return its + self._sweeps(max_iterations - its, tol_abs)
            play |= new
            idx = np.flatnonzero(play)
            dofs = _dofs(idx)
            sub = FrictionalContactSolver(self._block(idx, idx), self.mu[idx], layout="dense", check=False,
                                          anderson=self.anderson, reduce=False)
            r_play, info = sub.solve(q[dofs], tol_abs / (1.0 + np.linalg.norm(q[dofs])), max_iterations - its,
                                     r[dofs])
            its += info.iterations
            r = np.zeros(3 * self.n)
            r[dofs] = r_play
        self._r.from_numpy(r.astype(self._npr))
        self._u.from_numpy(u.astype(self._npr))
        self._last_error2 = error2
        return its

    def _auto(self, max_iterations, tol_abs):
        """Gauss-Seidel over the whole problem (most warm-started problems end within a few dozen
        sweeps, at a few µs a sweep) while every AUTO_PHASE sweeps at least halve the residual, at
        a rate that reaches the tolerance within AUTO_SWEEPS sweeps, in one launch; then Newton from where it stopped (the problems whose
        sweeps crawl: many coupled contacts, W ill-conditioned or singular)."""
        its = self._sweeps(min(AUTO_SWEEPS, max_iterations), tol_abs, AUTO_PHASE)
        if self._last_error2 <= tol_abs ** 2 or its >= max_iterations:
            return its
        return its + self._newton(max_iterations - its, tol_abs)

    def _newton(self, max_iterations, tol_abs):
        """Semi-smooth Newton (tissue.contact.newton) from the current r, on the host; Gauss-Seidel
        sweeps (this solver's kernel, with Anderson) are its fallback when a line search fails."""
        def fallback(r, sweeps):
            self._r.from_numpy(r.astype(self._npr))
            done = self._sweeps(sweeps, tol_abs) if sweeps else 0
            return self._r.to_numpy().astype(np.float64), done

        # A factored W stays factored: Newton reads W among the closing contacts once per solve
        # (newton._Shared) and products through the factors.
        r, u, its, err2 = newton.solve(self.W, self._block, self._q_host, self.mu, self._D_host,
                                       self._r.to_numpy().astype(np.float64), tol_abs, max_iterations, fallback,
                                       lambda r, u: _error2_numpy(r, u, self.mu))
        self._r.from_numpy(r.astype(self._npr))
        self._u.from_numpy(u.astype(self._npr))
        self._last_error2 = err2
        return its

    def _block(self, rows, cols) -> np.ndarray:
        """W between contacts `rows` and `cols` (ids), dense."""
        if self.layout == FACTORED:
            return self.W.block(rows, cols)
        r, c = _dofs(rows), _dofs(cols)
        if sp.issparse(self.W):                     # (also a small sparse W held densely)
            return self.W[r][:, c].toarray()
        return self.W[np.ix_(r, c)]

    def _jacobi(self, max_iterations, tol_abs):
        omega, best = self.omega, np.inf
        def matvec():
            _matvec(self.layout, *self._abc, self._q, self._r, self._u, self._y, self._z, self._scale)

        r_best = _array((3 * self.n,), backend.current().real)
        it = stalled = 0
        while True:
            matvec()
            if it % JACOBI_CHECK_EVERY == 0 or it >= max_iterations:
                _error2_kernel(self._r, self._u, self._mu, self._stats)
                err = float(np.sqrt(self._stats.to_numpy()[1]))
                if err <= tol_abs or it >= max_iterations:
                    break
                if err < best:
                    best, stalled = err, 0
                    r_best.copy_from(self._r)
                else:
                    stalled += 1
                # Diverging or cycling: back to the best iterate and relax harder.
                if (err > 2.0 * best or stalled >= JACOBI_STALL_CHECKS) and omega > 1e-6:
                    omega, stalled = 0.5 * omega, 0
                    self._r.copy_from(r_best)
                    matvec()
            _jacobi_step(self._Wd, self._mu, self._r, self._u, omega)
            it += 1
        if err > best:                              # hand back the best iterate seen
            self._r.copy_from(r_best)
        self.last_omega = omega
        return it


def solve_frictional_contact(W, q, mu, tol: float = 1e-6, max_iterations: int = 1000, r0=None,
                             method: str = "gauss_seidel", layout: str = "auto", anderson: int = ANDERSON_WINDOW,
                             reduce: bool = False):
    """Solve the frictional contact problem (W, q, mu); returns (r, ContactInfo).

    W: (3n, 3n) Delassus matrix, dense or scipy sparse; q: (3n,) free velocity; mu: scalar or (n,);
    per contact the order is (normal, tangent1, tangent2). Stops when the natural-map residual
    ||r - P_K(r - û)|| / (1 + ||q||) is <= tol or after max_iterations sweeps; r0 warm-starts.
    method: "gauss_seidel" (serial sweeps), "jacobi" (parallel, slower convergence), "newton"
    (semi-smooth Newton, for many coupled contacts) or "auto" (Gauss-Seidel, then Newton if the
    sweeps stall; the contact stage's default).
    layout: "auto" | "dense" | "csr" storage of W on the device (auto: block-CSR for a large sparse W).
    anderson: Gauss-Seidel's Anderson acceleration window (0: plain projected sweeps).
    reduce: method "gauss_seidel" on the contacts in play (pushed or touching) alone, W among them formed:
    faster when most contacts are apart and many sweeps are needed.
    Taichi must be initialised (tissue.backend.init). Bad input raises TissueError.
    """
    return FrictionalContactSolver(W, mu, method, layout, anderson=anderson, reduce=reduce).solve(
        q, tol, max_iterations, r0)
