"""The frictional contact problem by a semi-smooth Newton method on the Alart–Curnier function
(Alart & Curnier 1991; as Siconos' fc3d_nsn_ac), for the problems projected Gauss-Seidel cannot
finish: many strongly coupled contacts, more rows than the degrees of freedom they move (W
singular or nearly so), where a sweep's progress falls with W's conditioning and Newton's does not.

Problem and stopping rule: those of tissue.contact.frictional_contact (u = W r + q, Coulomb's law
per contact, the natural-map residual). Per contact, with ρ_t = 3 / tr W_ii, ρ_n = NORMAL_RHO ρ_t
(below SINGLE_ROWS rows; else ρ_t) and r̃_n = r_n - ρ_n u_n, r̃_t = r_t - ρ_t u_t,

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

Reused factors: a large Newton system (SINGLE_ROWS rows or more) changes from one step to the
next in the rows of the contacts whose state changed (stick/slide; closing or opening: rows and
columns), the sliding contacts' slip directions and the shift. Once at most REUSE_CHANGES of the
closing contacts changed state since the last LU, the step is solved by GMRES preconditioned by
that LU (on the contacts closing in both; see _preconditioner), a few O(k²) iterations instead
of an O(k³) factorisation, as an inexact Newton step (Dembo, Eisenstat & Steihaug 1982) whose
relative residual follows Φ's progress (Eisenstat & Walker 1996, within FORCING); a fresh LU when
GMRES does not get there within REUSE_ITERATIONS. Where no LU serves (a solve's first step, or
many contacts changed state since: the early steps of a solve from zero, which a factor would
serve once), GMRES preconditioned by J's 3×3 diagonal blocks first, within JACOBI_ITERATIONS
(each an O(k²) product): those steps' forcing is loose, and on the press plate it gets there in
tens of iterations, in a fraction of an LU's time. On the press plate (2,166 closing
rows, ~5-8 Newton steps a solve) the first, solved from zero, then takes no LU at all (4
before), the others 0-1 instead of 3 (5-7 with a fresh LU every step).

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
REUSE_CHANGES = 0.1      # a system of SINGLE_ROWS rows or more: GMRES preconditioned by the solve's last LU
                         # while at most this fraction of the closing contacts changed stick/slide state since,
REUSE_ITERATIONS = 12    # ... within this many iterations (else a fresh LU),
JACOBI_ITERATIONS = 100  # ... and where no LU serves: GMRES preconditioned by J's 3×3 diagonal blocks, within
                         # this many iterations, before a fresh LU
FORCING = (1e-3, 0.1)    # ... to a relative residual 0.9 (|Φ_k| / |Φ_k-1|)² clipped to this (Eisenstat-Walker)
NORMAL_RHO = 10.0        # ρ_n / ρ_t below SINGLE_ROWS rows (1 from there on): any ρ_n > 0 has the same solutions; a
                         # larger one weighs the normal velocities more in Φ and its merit. On the four of
                         # liver_press's Newton fallbacks that crawled (10-14 closing contacts, W among them near
                         # singular) ×10 took 6-18 Newton steps where ×1 took 14-31, from the same Gauss-Seidel
                         # start; ρ_t × 10 as well did no better there and failed (300 steps) on a singular soft-body
                         # problem from zero (tests); ρ_t alone × 10 did worse. On the press plate (2,382-3,465 rows)
                         # ×10 changed more contacts' states between Newton steps, GMRES on the last LU failed more
                         # often, and its solves took 11-16 % more CPU (the same Newton steps)


_I2 = np.eye(2)


def _rho(diagonal_blocks: np.ndarray) -> np.ndarray:
    """(ρ_n, ρ_t, ρ_t) per contact (n, 3): ρ_t = 3 / tr W_ii, ρ_n = NORMAL_RHO ρ_t below SINGLE_ROWS
    rows, else ρ_t (the Alart–Curnier augmentation, on W's scale)."""
    rho = 3.0 / np.trace(diagonal_blocks, axis1=1, axis2=2)
    return rho[:, None] * np.array([NORMAL_RHO if 3 * len(rho) < SINGLE_ROWS else 1.0, 1.0, 1.0])


def _alart_curnier(r: np.ndarray, u: np.ndarray, mu: np.ndarray, rho: np.ndarray, jacobian: bool = True):
    """Φ (n, 3) at reactions r and velocities u (both (n, 3)) with the augmentation rho (n, 3: ρ_n,
    ρ_t, ρ_t; see _rho), and the 3×3 blocks A, B (n, 3, 3) of its generalised Jacobian dΦ = A dr +
    B du (du = W dr). At the kinks the one-sided choice is the branch the strict inequality names
    (a valid element of the generalised Jacobian).
    Whole-array operations, no boolean-indexed assignments: the line search calls it a few times
    a Newton step on ~100 contacts, where each numpy call's overhead is most of its cost."""
    tilde = r - rho * u                                 # (r̃_n, r̃_t)
    closing = tilde[:, 0] > 0
    pressed = np.maximum(tilde[:, 0], 0.0)
    radius = mu * pressed
    rt_t = tilde[:, 1:]
    nt = np.sqrt(np.add.reduce(rt_t * rt_t, axis=1))    # |r̃_t| (as np.linalg.norm)
    stick = closing & (nt <= radius)
    slide = ~stick
    e = np.divide(rt_t, nt[:, None], out=np.zeros_like(rt_t), where=nt[:, None] > 0)
    projected = np.empty_like(tilde)                    # (max(0, r̃_n), P_disk(r̃_t))
    projected[:, 0] = pressed
    projected[:, 1:] = np.where(stick[:, None], rt_t, radius[:, None] * e)
    phi = r - projected
    if not jacobian:
        return phi, None, None
    n = len(mu)
    A, B = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    # Normal row: Φ_n = ρ_n u_n when closing, else r_n.
    A[:, 0, 0] = ~closing
    B[:, 0, 0] = np.where(closing, rho[:, 0], 0.0)
    # Sticking: Φ_t = ρ_t u_t. Sliding: Φ_t = r_t - R e, R = μ max(0, r̃_n), e = r̃_t / |r̃_t|:
    #   dΦ_t = dr_t - e dR - (R / |r̃_t|) (I - e eᵀ) dr̃_t, dR = μ (dr_n - ρ_n du_n) when closing.
    k = np.divide(radius, nt, out=np.zeros(n), where=slide & (nt > 0))
    G = k[:, None, None] * (_I2 - e[:, :, None] * e[:, None, :])     # (R / |r̃_t|)(I - e eᵀ)
    A[:, 1:, 1:] = np.where(slide[:, None, None], _I2 - G, 0.0)
    B[:, 1:, 1:] = rho[:, 1, None, None] * np.where(slide[:, None, None], G, _I2)
    pushing = (slide & closing)[:, None]
    A[:, 1:, 0] = np.where(pushing, -mu[:, None] * e, 0.0)
    B[:, 1:, 0] = np.where(pushing, (mu * rho[:, 0])[:, None] * e, 0.0)
    return phi, A, B


class _Shared:
    """What consecutive Newton steps of one solve share: W among the closing contacts, formed
    once while they stay the same (on the press plate's 2,166 closing rows a slice of W costs a
    third of the LU; the line search rarely changes which contacts close), W between them and the
    separating contacts still pushing (`carry`: after a step the line search cut, the same ones
    again; a block formed from W's factors is a Newton step's largest host cost on liver_press), and the last float32
    LU of a Newton system with each contact's state then (0 separating, 1 sticking, 2 sliding;
    see newton_step)."""

    def __init__(self):
        self.closing, self.Waa, self.lu, self.state = None, None, None, None
        self.carry, self.Wac = None, None


def newton_step(W, W_block, r, phi, A, B, closing, boost=1.0, shared=None, forcing=None):
    """dr solving (A + B W) dr = -Φ: dr_i = -Φ_i (= -r_i) for the separating contacts, then the
    closing ones from the dense system among them (LAPACK's LU, see _factor_solve, or GMRES on
    the last LU to relative residual `forcing`, FORCING[0] if None). W: the array, or anything
    with W @ r; W_block(rows, cols): W's (3|rows|, 3|cols|) block between contacts `rows` and
    `cols` (ids); shared: a _Shared kept between the steps of one solve."""
    shared = _Shared() if shared is None else shared
    dr = -phi.copy()
    act = closing.nonzero()[0]
    if not len(act):
        return dr
    a, k = len(act), 3 * len(act)
    rhs = -phi[act]
    carry = (~closing & (r != 0).any(axis=1)).nonzero()[0]      # separating, still pushing: dr = -r
    if shared.closing is None or not _same(shared.closing, act):
        all_closing = a == len(phi) and isinstance(W, np.ndarray)                  # (no copy)
        shared.closing, shared.Waa, shared.carry = act, W if all_closing else W_block(act, act), None
    if len(carry):
        if shared.carry is None or not _same(shared.carry, carry):
            shared.carry, shared.Wac = carry, W_block(act, carry)
        rhs -= np.matmul(B[act], (shared.Wac @ dr[carry].ravel()).reshape(a, 3, 1))[:, :, 0]
    Waa = shared.Waa
    J = np.matmul(B[act], Waa.reshape(a, 3, k)).reshape(k, k)
    idx = np.arange(a)
    J.reshape(a, 3, a, 3)[idx, :, idx, :] += A[act]
    shift = boost * min(max(REGULARISATION, np.linalg.norm(phi)), MAX_SHIFT)
    J.ravel()[::k + 1] += shift * max(np.abs(J.diagonal()).sum() / k, 1e-300)   # (its diagonal: J is contiguous)
    # Once few contacts change state from one step to the next, J differs from the last factorised
    # one in their rows (and columns, for those that close or open), the sliding contacts' slip
    # directions and the shift: GMRES preconditioned by the last LU then takes a few O(k²)
    # iterations, not a new O(k³) LU (bench.contact_auto_phase's "reused LU"). An inexact Newton
    # step (Dembo, Eisenstat & Steihaug 1982): its relative residual `forcing` (solve's, small once
    # Φ falls fast) keeps the convergence fast.
    state = np.zeros(len(phi), np.int8)
    state[act] = 1 + A[act].any(axis=(1, 2))        # (a closing contact's A is zero iff it sticks)
    x, forcing = None, FORCING[0] if forcing is None else forcing
    if shared.lu is not None and np.count_nonzero(state != shared.state) <= REUSE_CHANGES * a:
        x = _gmres(J, rhs.ravel(), _preconditioner(J, shared.lu, np.flatnonzero(shared.state), act),
                   forcing, REUSE_ITERATIONS)
    if x is None and k >= SINGLE_ROWS:
        # No LU to reuse (the first step, or many contacts changed state: the early steps of a
        # solve from zero): GMRES preconditioned by J's diagonal blocks often reaches the loose
        # forcing of those steps for less than an LU, which would serve only them.
        inverses = _diagonal_inverses(J, idx)
        x = _gmres(J, rhs.ravel(), lambda v: np.einsum("iab,ib->ia", inverses, v.reshape(-1, 3)).ravel(),
                   forcing, JACOBI_ITERATIONS)
    if x is None:
        x, shared.lu = _factor_solve(J, rhs.ravel(), forcing)
        shared.state = state
    dr[act] = x.reshape(-1, 3)
    return dr


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """np.array_equal(a, b) of two index arrays, without its Python overhead (a few µs a call, a
    few calls a Newton step on ~100 contacts)."""
    return a.shape == b.shape and bool((a == b).all())


def _lu_solve(J, b):
    """J⁻¹ b by LAPACK's LU (see _factor_solve)."""
    return _factor_solve(J, b)[0]


def _factor_solve(J, b, tol=REFINED):
    """(x, its float32 LU or None) with |J x - b| <= max(tol, REFINED) |b| by LAPACK's LU; from
    SINGLE_ROWS rows on, factorised in float32 (half the time) and refined in float64 (a few
    residuals J x - b, one O(k²) product each) only as far as tol asks (an inexact Newton step
    needs no more than GMRES's: Newton's first steps, whose states change most, take tol 0.1), in
    float64 outright where the refinement does not get there (J too ill-conditioned for float32;
    no factor returned then). J may be overwritten."""
    if len(b) >= SINGLE_ROWS:
        lu = _lu(J.astype(np.float32))
        x = np.zeros_like(b)
        residual = b
        for _ in range(REFINEMENTS):
            x += _lu_apply(lu, residual.astype(np.float32))
            residual = b - J @ x
            if np.linalg.norm(residual) <= max(tol, REFINED) * np.linalg.norm(b):
                return x, lu
    return _lu_apply(_lu(J), b), None


def _lu(J):
    """LAPACK's LU of J (float32 or float64; overwritten) as (lu, pivots), getrf called outright:
    scipy.linalg.lu_factor and lu_solve call the same getrf and getrs (the same bits) through
    wrappers that cost more than factorising liver_press's ~36-row systems."""
    getrf = scipy.linalg.lapack.sgetrf if J.dtype == np.float32 else scipy.linalg.lapack.dgetrf
    lu, pivots, _ = getrf(J, overwrite_a=True)
    return lu, pivots


def _lu_apply(lu, b):
    """J⁻¹ b from _lu's (lu, pivots) of J, in their precision (getrs)."""
    getrs = scipy.linalg.lapack.sgetrs if lu[0].dtype == np.float32 else scipy.linalg.lapack.dgetrs
    return getrs(*lu, b)[0]


def _preconditioner(J, lu, before, act):
    """v -> an approximation of J⁻¹ v (J the Newton system among the closing contacts `act`, ids)
    from lu, the float32 LU of an earlier one among the contacts `before`: its solve on the
    contacts in both (zero on those no longer closing), the inverse of J's 3×3 diagonal block on
    those closing since."""
    def solve(v):
        return _lu_apply(lu, v.astype(np.float32))

    if np.array_equal(before, act):
        return solve
    both = np.isin(act, before)
    old, new = _dofs(np.searchsorted(before, act[both])), _dofs(np.flatnonzero(both))
    fresh = np.flatnonzero(~both)
    inverses = _diagonal_inverses(J, fresh)

    def apply(v):
        w = np.zeros(3 * len(before))
        w[old] = v[new]
        out = np.empty_like(v)
        out[new] = solve(w)[old]
        out[_dofs(fresh)] = np.einsum("iab,ib->ia", inverses, v[_dofs(fresh)].reshape(-1, 3)).ravel()
        return out

    return apply


def _diagonal_inverses(J, contacts):
    """The (pseudo-)inverses of J's 3×3 diagonal blocks of `contacts` (positions among J's)."""
    a = J.shape[0] // 3
    return np.linalg.pinv(J.reshape(a, 3, a, 3)[contacts, :, contacts, :])


def _dofs(contacts):
    """The rows 3i, 3i + 1, 3i + 2 of each contact i."""
    return (3 * np.asarray(contacts)[:, None] + np.arange(3)).ravel()


def _gmres(J, b, precondition, tol, iterations):
    """x with |J x - b| <= tol |b| by GMRES (Saad & Schultz 1986), preconditioned on the right
    by precondition(v) ≈ J⁻¹ v (from the LU of a nearby matrix), or None when `iterations` do not
    reach it (or, from the third on, would not at the rate so far: a fresh LU costs less then). The
    preconditioned vectors are kept (as flexible GMRES does), so x is J's own least-squares
    combination whatever the float32 rounding; the residual is checked afresh at the end."""
    beta = np.linalg.norm(b)
    if beta == 0.0:
        return np.zeros_like(b)
    V, Z = np.empty((iterations + 1, len(b))), np.empty((iterations, len(b)))
    H = np.zeros((iterations + 1, iterations))
    V[0] = b / beta
    for j in range(iterations):
        Z[j] = precondition(V[j])
        w = J @ Z[j]
        for _ in range(2):                          # classical Gram-Schmidt, twice: orthogonal to rounding
            h = V[:j + 1] @ w
            w -= h @ V[:j + 1]
            H[:j + 1, j] += h
        H[j + 1, j] = np.linalg.norm(w)
        e1 = np.zeros(j + 2)
        e1[0] = beta
        y = np.linalg.lstsq(H[:j + 2, :j + 1], e1, rcond=None)[0]
        fraction = np.linalg.norm(H[:j + 2, :j + 1] @ y - e1) / beta
        if fraction <= 0.5 * tol or H[j + 1, j] == 0.0:
            x = y @ Z[:j + 1]
            return x if np.linalg.norm(J @ x - b) <= tol * beta else None
        if j >= 2 and fraction ** (iterations / (j + 1)) > tol:
            return None                             # at its rate so far it would not get there: stop early
        V[j + 1] = w / H[j + 1, j]
    return None


def solve(W, W_block, q, mu, diagonal_blocks, r0, tol_abs, max_iterations, gauss_seidel, error2):
    """Newton iterations from r0 until the natural-map error is at most tol_abs (absolute) or
    max_iterations (Newton steps and fallback sweeps together). W: anything with W @ r; W_block:
    see newton_step; gauss_seidel(r, sweeps) -> (r, sweeps done): the fallback; error2(r, u): the
    squared natural-map error. Returns (r, u, iterations, error²)."""
    n = len(mu)
    rho = _rho(diagonal_blocks)
    r = np.asarray(r0, dtype=np.float64).reshape(n, 3).copy()
    its, boost, shared = 0, 1.0, _Shared()
    anchor, eps, inner, previous = None, 0.0, 0, None
    u, exact = None, False
    while True:
        # u follows the accepted steps (u + t W dr: one product a step); the stopping rule reads
        # u afresh, W r + q, before it stops, as it does after a Gauss-Seidel fallback.
        if u is None:
            u, exact = (W @ r.ravel() + q).reshape(n, 3), True
        err2 = error2(r.ravel(), u.ravel())
        if err2 <= tol_abs ** 2 or its >= max_iterations:
            if not exact:
                u = None
                continue
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
        merit = 0.5 * (phi * phi).sum()
        closing = r[:, 0] - rho[:, 0] * ue[:, 0] > 0
        # Newton's linear solves need be no more exact than Φ's progress shows the model to be
        # (Eisenstat & Walker 1996, choice 2): loose while states change and Φ falls slowly.
        low, high = FORCING
        forcing = low if previous is None else float(min(max(0.9 * (2.0 * merit / previous ** 2), low), high))
        previous = np.sqrt(2.0 * merit)
        if anchor is None:
            dr = newton_step(W, W_block, r, phi, A, B, closing, boost, shared, forcing)
            wdr = du = (W @ dr.ravel()).reshape(n, 3)
        else:
            block = lambda rows, cols: W_block(rows, cols) + (eps * np.eye(3 * len(rows)) if rows is cols else 0.0)
            dr = newton_step(None, block, r, phi, A, B, closing, boost, shared)
            wdr = (W @ dr.ravel()).reshape(n, 3)
            du = wdr + eps * dr
            inner += 1
        t, accepted = 1.0, False
        for _ in range(BACKTRACKS):
            trial = _alart_curnier(r + t * dr, ue + t * du, mu, rho, jacobian=False)[0]
            if 0.5 * (trial * trial).sum() <= (1.0 - 2.0 * ARMIJO * t) * merit:
                accepted = True
                break
            t *= 0.5
        its += 1
        # Levenberg–Marquardt's rule: a step cut by the line search had too small a shift (along
        # W's near-null space it overshoots), a full one could take less.
        boost = max(1.0, 0.1 * boost) if t == 1.0 else min(BOOST_MAX, 10.0 * boost)
        if accepted:
            r += t * dr
            u, exact = u + t * wdr, False
        else:
            r, sweeps = gauss_seidel(r.ravel(), min(GS_FALLBACK, max(0, max_iterations - its)))
            r, u = r.reshape(n, 3), None
            its += sweeps
