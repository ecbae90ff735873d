"""The frictional contact problem by a semi-smooth Newton method on the Alart–Curnier function
(Alart & Curnier 1991; as Siconos' fc3d_nsn_ac), for the problems projected Gauss-Seidel cannot
finish: many strongly coupled contacts, more rows than the degrees of freedom they move (W
singular or nearly so), where a sweep's progress falls with W's conditioning and Newton's does not.

Problem and stopping rule: those of tissue.contact.frictional_contact (u = W r + q, Coulomb's law
per contact, the natural-map residual). Per contact, with ρ = 3 / tr W_ii and
r̃_n = r_n - ρ u_n, r̃_t = r_t - ρ u_t,

    Φ_n = r_n - max(0, r̃_n),     Φ_t = r_t - P_{disk(μ max(0, r̃_n))}(r̃_t),

zero exactly at a solution of the same problem. Φ is piecewise smooth; its generalised Jacobian
is dΦ = A dr + B W dr with A, B block diagonal (3×3 per contact, `_alart_curnier`). A Newton step
solves (A + B W) dr = -Φ. Contacts with r̃_n ≤ 0 (separating) have A = I, B = 0, so their step is
dr_i = -r_i outright; only the others ("closing") enter the linear system, with W among them
(and, on the right, W between them and the separating contacts that still carry a reaction). Within
an alarm distance most contacts separate, so that system is small; of the press plate's 722
contacts 340-722 close, a system of up to ~2,100² (a dense LU, LAPACK; from SINGLE_ROWS rows on
in float32, refined in float64: half the time). A multiple ε of the identity keeps it solvable
where W is singular (with more contact rows than the dofs they move, sticking contacts' rows of W
are dependent): ε = boost × clip(|Φ|, REGULARISATION, MAX_SHIFT) times the system's mean
diagonal, a Levenberg–Marquardt-like shift that vanishes with Φ (so the local convergence stays
fast) but damps the steps along W's null space far from the solution, where a fixed 1e-10 let
them grow without bound and stall the line search (tests: 300 contacts on 60 nodes). `boost`
follows Levenberg–Marquardt's rule: ×10 after a step the line search cut, ÷10 (down to 1) after a
full one; without it, steps near a solution on singular W (liver_press: 12 closing contacts whose
rows outnumber their nodes' dofs) were cut to tiny ones, and Newton crawled to the cap.

Globalisation: a backtracking line search on ½|Φ|² (Armijo); when it fails (nonsmooth kinks, a
singular step), GS_FALLBACK sweeps of projected Gauss-Seidel from the current r, then Newton again.

Crawling (the shift's boost at CRAWL: steps cut again and again): proximal points (Rockafellar
1976) from there on. With more rows than the dofs they move, reactions can shift along W's null
space without changing any velocity, and a solution may lie a finite distance along it (the
cones decide where); the shift damps exactly those steps, and Newton crawled there (liver_press
at 450 rows: 12 closing contacts, |Φ| falling by 1 % a step to the cap; Gauss-Seidel's sweeps no
better). A proximal point solves the problem (W + εI, q - ε r_k) instead, W + εI definite, with
ε = PROXIMAL × W's mean diagonal: its solution r_{k+1} is unique and Newton's steps on it are
not damped along the null space; the anchor r_k moves to the iterate after PROXIMAL_STEPS steps,
or once the subproblem's |Φ| is at most PROXIMAL_INNER of the true problem's error, and a fixed
point (r_{k+1} = r_k) solves the true problem, whose error, not the subproblem's, stops the
iterations.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

REGULARISATION = 1e-10   # the least shift of the Newton system (× its mean diagonal): solvable when W is singular
MAX_SHIFT = 1e-3         # the most: the shift is |Φ| between the two
ARMIJO = 1e-4            # sufficient decrease of ½|Φ|² along the step
BACKTRACKS = 20          # halvings of the step before the line search gives up
BOOST_MAX = 1e8          # the shift grows tenfold after each step the line search cut, to at most this factor
SINGLE_ROWS = 600        # Newton systems of this many rows and more: LU in float32, refined in float64
REFINEMENTS = 4          # ... at most this many solves with it
REFINED = 1e-10          # ... to this relative residual, else float64's LU
CRAWL = 1e3              # proximal points once the boost reaches this (three steps cut net)
PROXIMAL = 1e-3          # ... ε of W + εI, × W's mean diagonal
PROXIMAL_STEPS = 5       # ... Newton steps on one proximal problem at most
PROXIMAL_INNER = 0.1     # ... or until its |Φ| is at most this fraction of the true problem's error
GS_FALLBACK = 10         # Gauss-Seidel sweeps run when the line search gives up


def _rho(diagonal_blocks: np.ndarray) -> np.ndarray:
    """ρ per contact: 3 / tr W_ii (the Alart–Curnier augmentation, on W's scale)."""
    return 3.0 / np.trace(diagonal_blocks, axis1=1, axis2=2)


def _alart_curnier(r: np.ndarray, u: np.ndarray, mu: np.ndarray, rho: np.ndarray, jacobian: bool = True):
    """Φ (n, 3) at reactions r and velocities u (both (n, 3)), and the 3×3 blocks A, B (n, 3, 3) of
    its generalised Jacobian dΦ = A dr + B du (du = W dr). At the kinks the one-sided choice
    is the branch the strict inequality names (a valid element of the generalised Jacobian)."""
    n = len(mu)
    rn_t = r[:, 0] - rho * u[:, 0]
    rt_t = r[:, 1:] - rho[:, None] * u[:, 1:]
    closing = rn_t > 0
    radius = mu * np.maximum(rn_t, 0.0)
    nt = np.linalg.norm(rt_t, axis=1)
    stick = closing & (nt <= radius)
    slide = ~stick
    phi = np.empty((n, 3))
    phi[:, 0] = r[:, 0] - np.maximum(rn_t, 0.0)
    e = np.divide(rt_t, nt[:, None], out=np.zeros_like(rt_t), where=nt[:, None] > 0)
    phi[:, 1:] = np.where(stick[:, None], r[:, 1:] - rt_t, r[:, 1:] - radius[:, None] * e)
    if not jacobian:
        return phi, None, None
    A, B = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    # Normal row: Φ_n = ρ u_n when closing, else r_n.
    A[~closing, 0, 0] = 1.0
    B[closing, 0, 0] = rho[closing]
    # Sticking: Φ_t = ρ u_t.
    B[stick, 1, 1] = B[stick, 2, 2] = rho[stick]
    # Sliding: Φ_t = r_t - R e, R = μ max(0, r̃_n), e = r̃_t / |r̃_t|:
    #   dΦ_t = dr_t - e dR - (R / |r̃_t|) (I - e eᵀ) dr̃_t, dR = μ (dr_n - ρ du_n) when closing.
    s = np.flatnonzero(slide)
    es, ks = e[s], np.divide(radius[s], nt[s], out=np.zeros(len(s)), where=nt[s] > 0)
    G = ks[:, None, None] * (np.eye(2) - es[:, :, None] * es[:, None, :])     # (R / |r̃_t|)(I - e eᵀ)
    A[s, 1:, 1:] = np.eye(2) - G
    B[s, 1:, 1:] = rho[s, None, None] * G
    c = closing[s]
    A[s[c], 1:, 0] = -mu[s[c], None] * es[c]
    B[s[c], 1:, 0] = (mu[s[c]] * rho[s[c]])[:, None] * es[c]
    return phi, A, B


class _Shared:
    """What consecutive Newton steps of one solve share: W among the closing contacts, formed
    once while they stay the same (on the press plate's 2,166 closing rows a slice of W costs
    a third of the LU; the line search rarely changes which contacts close)."""

    def __init__(self):
        self.closing, self.Waa = None, None


def newton_step(W, W_block, r, phi, A, B, closing, boost=1.0, shared=None):
    """dr solving (A + B W) dr = -Φ: dr_i = -Φ_i (= -r_i) for the separating contacts, then the
    closing ones from the dense system among them (LAPACK's LU; see _lu_solve). W: the array, or
    anything with W @ r; W_block(rows, cols): W's (3|rows|, 3|cols|) block between contacts
    `rows` and `cols` (ids); shared: a _Shared kept between the steps of one solve."""
    shared = _Shared() if shared is None else shared
    dr = -phi.copy()
    act = np.flatnonzero(closing)
    if not len(act):
        return dr
    a, k = len(act), 3 * len(act)
    rhs = -phi[act]
    carry = np.flatnonzero(~closing & (r != 0).any(axis=1))      # separating, still pushing: dr = -r
    if len(carry):
        rhs -= np.matmul(B[act], (W_block(act, carry) @ dr[carry].ravel()).reshape(a, 3, 1))[:, :, 0]
    if shared.closing is None or not np.array_equal(shared.closing, act):
        all_closing = a == len(phi) and isinstance(W, np.ndarray)                  # (no copy)
        shared.closing, shared.Waa = act, W if all_closing else W_block(act, act)
    Waa = shared.Waa
    J = np.matmul(B[act], Waa.reshape(a, 3, k)).reshape(k, k)
    idx = np.arange(a)
    J.reshape(a, 3, a, 3)[idx, :, idx, :] += A[act]
    shift = boost * min(max(REGULARISATION, np.linalg.norm(phi)), MAX_SHIFT)
    J[np.diag_indices(k)] += shift * max(np.mean(np.abs(np.diag(J))), 1e-300)
    dr[act] = _lu_solve(J, rhs.ravel()).reshape(-1, 3)
    return dr


def _lu_solve(J, b):
    """J⁻¹ b by LAPACK's LU; from SINGLE_ROWS rows on, factorised in float32 (half the time) and
    refined in float64 (a few residuals J x - b, one O(k²) product each), in float64 outright
    where the refinement does not reach REFINED (J too ill-conditioned for float32)."""
    if len(b) >= SINGLE_ROWS:
        lu = scipy.linalg.lu_factor(J.astype(np.float32), overwrite_a=True, check_finite=False)
        x = np.zeros_like(b)
        residual = b
        for _ in range(REFINEMENTS):
            x += scipy.linalg.lu_solve(lu, residual.astype(np.float32), check_finite=False)
            residual = b - J @ x
            if np.linalg.norm(residual) <= REFINED * np.linalg.norm(b):
                return x
    return scipy.linalg.lu_solve(scipy.linalg.lu_factor(J, overwrite_a=True, check_finite=False), b, check_finite=False)


def solve(W, W_block, q, mu, diagonal_blocks, r0, tol_abs, max_iterations, gauss_seidel, error2):
    """Newton iterations from r0 until the natural-map error is at most tol_abs (absolute) or
    max_iterations (Newton steps and fallback sweeps together). W: anything with W @ r; W_block:
    see newton_step; gauss_seidel(r, sweeps) -> (r, sweeps done): the fallback; error2(r, u): the
    squared natural-map error. Returns (r, u, iterations, error²)."""
    n = len(mu)
    rho = _rho(diagonal_blocks)
    r = np.asarray(r0, dtype=np.float64).reshape(n, 3).copy()
    its, boost, shared = 0, 1.0, _Shared()
    anchor, eps, inner = None, 0.0, 0
    while True:
        u = (W @ r.ravel() + q).reshape(n, 3)          # afresh: the stopping rule reads the exact u
        err2 = error2(r.ravel(), u.ravel())
        if err2 <= tol_abs ** 2 or its >= max_iterations:
            return r.ravel(), u.ravel(), its, err2
        if anchor is None and boost >= CRAWL:
            # Crawling: proximal points from here on (see the module docstring); W_block among
            # the closing contacts (the same ids twice) then carries + εI.
            eps = PROXIMAL * np.mean(np.trace(diagonal_blocks, axis1=1, axis2=2)) / 3.0
            anchor, inner, boost, shared = r.copy(), 0, 1.0, _Shared()
        if anchor is not None and inner >= PROXIMAL_STEPS:
            anchor, inner = r.copy(), 0
        ue = u if anchor is None else u + eps * (r - anchor)   # the velocities of the problem stepped on
        phi, A, B = _alart_curnier(r, ue, mu, rho)
        if anchor is not None and inner and np.linalg.norm(phi) <= PROXIMAL_INNER * np.sqrt(err2):
            anchor, inner, ue = r.copy(), 0, u
            phi, A, B = _alart_curnier(r, ue, mu, rho)
        merit = 0.5 * np.sum(phi * phi)
        closing = r[:, 0] - rho * ue[:, 0] > 0
        if anchor is None:
            dr = newton_step(W, W_block, r, phi, A, B, closing, boost, shared)
            du = (W @ dr.ravel()).reshape(n, 3)
        else:
            block = lambda rows, cols: W_block(rows, cols) + (eps * np.eye(3 * len(rows)) if rows is cols else 0.0)
            dr = newton_step(None, block, r, phi, A, B, closing, boost, shared)
            du = (W @ dr.ravel()).reshape(n, 3) + eps * dr
            inner += 1
        t, accepted = 1.0, False
        for _ in range(BACKTRACKS):
            trial = _alart_curnier(r + t * dr, ue + t * du, mu, rho, jacobian=False)[0]
            if 0.5 * np.sum(trial * trial) <= (1.0 - 2.0 * ARMIJO * t) * merit:
                accepted = True
                break
            t *= 0.5
        its += 1
        # Levenberg–Marquardt's rule: a step cut by the line search had too small a shift (along
        # W's near-null space it overshoots), a full one could take less.
        boost = max(1.0, 0.1 * boost) if t == 1.0 else min(BOOST_MAX, 10.0 * boost)
        if accepted:
            r += t * dr
        else:
            r, sweeps = gauss_seidel(r.ravel(), min(GS_FALLBACK, max(0, max_iterations - its)))
            r = r.reshape(n, 3)
            its += sweeps
