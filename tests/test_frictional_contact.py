"""The frictional contact solver against independent references: LCP by enumeration and by a QP,
hand-derived single-contact and block-on-a-plane solutions, and the natural-map residual of random
problems recomputed here (not with the module's own residual)."""

import itertools
import time

import numpy as np
import pytest
import scipy.optimize
import scipy.sparse as sp

from tissue.errors import TissueError

# ----------------------------------------------------------------------------------------------
# independent helpers
# ----------------------------------------------------------------------------------------------


def natural_map(W, q, mu, r):
    """||r - P_K(r - û)|| / (1 + ||q||), û = (u_n + mu |u_t|, u_t), written contact by contact."""
    u = W @ r + q
    n = len(q) // 3
    mu = np.broadcast_to(mu, (n,))
    err = 0.0
    for i in range(n):
        ri, ui, m = r[3 * i:3 * i + 3], u[3 * i:3 * i + 3], mu[i]
        x = ri - ui - np.array([m * np.hypot(ui[1], ui[2]), 0.0, 0.0])
        nt = np.hypot(x[1], x[2])
        if nt <= m * x[0]:
            p = x                                        # inside the cone
        elif m * nt <= -x[0]:
            p = np.zeros(3)                              # inside the polar cone
        else:
            a = (x[0] + m * nt) / (1 + m * m)
            p = np.array([a, m * a * x[1] / nt, m * a * x[2] / nt])
        err += np.sum((ri - p) ** 2)
    return np.sqrt(err) / (1 + np.linalg.norm(q))


def frame(normal):
    nrm = normal / np.linalg.norm(normal)
    a = np.array([1.0, 0, 0]) if abs(nrm[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = np.cross(nrm, a)
    t1 /= np.linalg.norm(t1)
    return np.stack([nrm, t1, np.cross(nrm, t1)])


def skew(p):
    return np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])


def random_delassus(n, rng):
    """W = J M^-1 J^T with a random full-rank J (more dofs than constraints) and a random SPD M."""
    d = 3 * n + 3
    J = rng.standard_normal((3 * n, d))
    B = rng.standard_normal((d, d))
    M = B @ B.T + d * np.eye(d)
    W = J @ np.linalg.solve(M, J.T)
    return 0.5 * (W + W.T) * d                           # scaled so that r is O(1)


def soft_body_problem(nc, nnodes, rng, h=0.04, k=50.0):
    """Contacts on triangles of a soft body: W = H (h A^-1) H^T, A = I + h^2 k L (x) I3 with L the
    Laplacian of a random nearest-neighbour graph (dense compliance, as the paper's warped A0^-1)."""
    P = rng.random((nnodes, 3))
    nb = np.argsort(np.linalg.norm(P[:, None] - P[None], axis=2), axis=1)[:, 1:7]
    L = np.zeros((nnodes, nnodes))
    L[np.repeat(np.arange(nnodes), 6), nb.ravel()] = -1
    L = np.minimum(L, L.T)
    L -= np.diag(L.sum(1))
    C = h * np.linalg.inv(np.kron(np.eye(nnodes) + h * h * k * L, np.eye(3)))
    H = np.zeros((3 * nc, 3 * nnodes))
    for c in range(nc):
        F = frame(rng.standard_normal(3))
        for node, w in zip(rng.choice(nnodes, 3, replace=False), rng.dirichlet(np.ones(3))):
            H[3 * c:3 * c + 3, 3 * node:3 * node + 3] += w * F
    W = H @ C @ H.T
    q = np.column_stack([rng.uniform(-1, 0.3, nc), 0.5 * rng.standard_normal((nc, 2))]).ravel()
    return 0.5 * (W + W.T), q, rng.uniform(0.1, 0.7, nc)


def rigid_bodies_problem(nb, nc, rng, pair_fraction=0.3):
    """Rigid boxes touching the ground or each other; W = J M^-1 J^T is 3x3-block sparse (and rank
    deficient: several contacts per body)."""
    Minv = sp.block_diag([sp.diags(np.r_[np.full(3, 1 / rng.uniform(0.5, 2)), 1 / rng.uniform(0.05, 0.2, 3)])
                          for _ in range(nb)]).tocsr()
    rows, cols, vals = [], [], []
    for c in range(nc):
        a = rng.integers(nb)
        b = rng.integers(nb) if rng.random() < pair_fraction else -1
        F = frame(np.array([0, 0, 1.0]) + 0.2 * rng.standard_normal(3))
        for body, sign in ((a, 1.0), (b, -1.0)):
            if body < 0 or (body == a and sign < 0):
                continue
            p = rng.uniform(-0.5, 0.5, 3)
            Jb = sign * np.hstack([F, -F @ skew(p)])     # relative velocity at p, in the contact frame
            ii, jj = np.meshgrid(np.arange(3 * c, 3 * c + 3), np.arange(6 * body, 6 * body + 6), indexing="ij")
            rows.append(ii.ravel()), cols.append(jj.ravel()), vals.append(Jb.ravel())
    J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * nc, 6 * nb))
    v = 0.3 * rng.standard_normal(6 * nb)
    v[2::6] -= 1.0                                       # falling onto the ground
    return (J @ Minv @ J.T).tocsr(), J @ v, rng.uniform(0.1, 0.7, nc)


def lcp_by_enumeration(A, b):
    """The solution of 0 <= A x + b ⊥ x >= 0 (A SPD): try every active set."""
    n = len(b)
    for k in range(n + 1):
        for S in itertools.combinations(range(n), k):
            S = list(S)
            x = np.zeros(n)
            if S:
                x[S] = np.linalg.solve(A[np.ix_(S, S)], -b[S])
            if np.all(x >= -1e-12) and np.all(A @ x + b >= -1e-12):
                return x
    raise AssertionError("no active set solves the LCP")


@pytest.fixture(scope="module")
def solve(backend):
    from tissue.contact import solve_frictional_contact
    return solve_frictional_contact


# ----------------------------------------------------------------------------------------------
# frictionless: the LCP
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(8))
def test_frictionless_matches_enumeration_and_qp(solve, seed):
    rng = np.random.default_rng(seed)
    n = 1 + seed % 6
    W = random_delassus(n, rng)
    q = rng.standard_normal(3 * n)
    r, info = solve(W, q, 0.0, tol=1e-12, max_iterations=10000)
    assert info.converged, info
    Wn, qn = W[0::3, 0::3], q[0::3]
    ref = lcp_by_enumeration(Wn, qn)
    np.testing.assert_allclose(r[0::3], ref, atol=1e-6)
    assert np.all(r[1::3] == 0) and np.all(r[2::3] == 0)
    qp = scipy.optimize.minimize(lambda x: (0.5 * x @ Wn @ x + qn @ x, Wn @ x + qn), np.zeros(n), jac=True,
                                 method="L-BFGS-B", bounds=[(0, None)] * n,
                                 options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000})
    np.testing.assert_allclose(r[0::3], qp.x, atol=1e-6)


# ----------------------------------------------------------------------------------------------
# one contact, by hand
# ----------------------------------------------------------------------------------------------

def test_single_contact_stick_slide_separate(solve):
    # W = diag(wn, wt, wt), u = W r + q. Closing (q_n < 0): u_n = 0 gives r_n = -q_n / wn.
    # Stick (u_t = 0): r_t = -q_t / wt, valid iff |q_t| / wt <= mu r_n.
    # Slide: r_t = -mu r_n q_t / |q_t|, u_t = q_t (1 - wt mu r_n / |q_t|) (same direction as q_t).
    wn, wt, mu = 2.0, 0.5, 0.4
    W = np.diag([wn, wt, wt])
    rn = 1.5
    qn = -wn * rn
    for qt, sticks in (([0.1, -0.2], True), ([0.8, 0.6], False)):
        qt = np.array(qt)
        assert (np.linalg.norm(qt) / wt <= mu * rn) == sticks
        r, info = solve(W, np.r_[qn, qt], mu, tol=1e-14)
        expect_t = -qt / wt if sticks else -mu * rn * qt / np.linalg.norm(qt)
        np.testing.assert_allclose(r, np.r_[rn, expect_t], rtol=1e-13, atol=1e-15)
        u = W @ r + np.r_[qn, qt]
        if not sticks:
            np.testing.assert_allclose(u[1:], qt * (1 - wt * mu * rn / np.linalg.norm(qt)), rtol=1e-12)
        assert info.iterations <= 2                       # the local solve is exact
    r, info = solve(W, np.array([0.3, 5.0, -1.0]), mu)   # separating: no force at all
    assert np.all(r == 0) and info.iterations == 0


def test_single_contact_coupled_block_is_exact(solve):
    # A general SPD 3x3 block (normal and tangents coupled): check the Coulomb law case by case.
    rng = np.random.default_rng(3)
    slides = 0
    for _ in range(50):
        B = rng.standard_normal((3, 3))
        A = B @ B.T + 0.05 * np.eye(3)
        q = rng.standard_normal(3)
        q[0] = -abs(q[0])
        mu = rng.uniform(0.05, 1.0)
        r, info = solve(A, q, mu, tol=1e-12)
        u = A @ r + q
        rt, ut = np.hypot(r[1], r[2]), np.hypot(u[1], u[2])
        assert natural_map(A, q, mu, r) < 1e-12
        assert r[0] >= 0 and abs(u[0]) < 1e-12 * (1 + abs(q).max())  # closing contact: u_n = 0
        if ut > 1e-10:                                    # sliding: on the cone, opposing u_t
            slides += 1
            assert rt == pytest.approx(mu * r[0], rel=1e-10)
            np.testing.assert_allclose(r[1:] / rt, -u[1:] / ut, atol=1e-8)
        else:
            assert rt <= mu * r[0] * (1 + 1e-12)
    assert 10 < slides < 50                               # both regimes were exercised


# ----------------------------------------------------------------------------------------------
# a rigid block on a plane
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("push_ratio, sticks", [(0.5, True), (0.95, True), (1.5, False)])
def test_block_on_plane(solve, push_ratio, sticks):
    m, g, h, mu = 2.0, 9.81, 0.01, 0.5
    a, b, c = 0.5, 0.3, 0.2                               # half extents; contacts at the bottom corners
    I = m / 3 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    Minv = np.zeros((6, 6))
    Minv[:3, :3], Minv[3:, 3:] = np.eye(3) / m, np.linalg.inv(I)
    corners = [np.array([sx * a, sy * b, -c]) for sx in (-1, 1) for sy in (-1, 1)]
    J = np.vstack([np.hstack([np.eye(3), -skew(p)]) for p in corners])   # frame (z; x, y)
    J = J[np.array([[3 * i + 2, 3 * i, 3 * i + 1] for i in range(4)]).ravel()]
    push = push_ratio * mu * m * g
    v_free = h * Minv @ np.r_[push, 0, -m * g, 0, 0, 0]  # push along x at the centre of mass
    W, q = J @ Minv @ J.T, J @ v_free
    r, info = solve(W, q, mu, tol=1e-10, max_iterations=20000)
    assert info.converged and natural_map(W, q, mu, r) <= 1e-10
    R = r.reshape(4, 3)
    v = v_free + Minv @ J.T @ r                           # the body's velocity after the step
    assert R[:, 0].sum() == pytest.approx(h * m * g, rel=1e-6)
    if sticks:
        np.testing.assert_allclose(v, 0, atol=1e-8)       # every contact point at rest
        assert R[:, 1].sum() == pytest.approx(-h * push, rel=1e-6)   # friction balances the push
    else:
        assert v[0] == pytest.approx(h * (push - mu * m * g) / m, rel=1e-6)
        np.testing.assert_allclose(v[1:], 0, atol=1e-8)
        loaded = R[:, 0] > 1e-9
        np.testing.assert_allclose(np.hypot(R[loaded, 1], R[loaded, 2]), mu * R[loaded, 0], rtol=1e-6)
        assert R[:, 1].sum() == pytest.approx(-mu * h * m * g, rel=1e-6)


# ----------------------------------------------------------------------------------------------
# random frictional problems
# ----------------------------------------------------------------------------------------------

def _report(label, info, n):
    print(f"\n{label}: {n} contacts, {info.iterations} iterations, residual {info.residual:.2e}, "
          f"{info.time_s * 1e3:.1f} ms")


def test_soft_body_300_contacts(solve):
    W, q, mu = soft_body_problem(300, 600, np.random.default_rng(0))
    solve(W, q, mu, max_iterations=1)                     # compile outside the timing
    r, info = solve(W, q, mu, tol=1e-6, max_iterations=1000)
    _report("gauss-seidel dense", info, 300)
    assert info.converged and natural_map(W, q, mu, r) <= 1e-6
    R = r.reshape(-1, 3)
    assert np.all(R[:, 0] >= 0) and np.all(np.hypot(R[:, 1], R[:, 2]) <= mu * R[:, 0] * (1 + 1e-12))
    # Jacobi gets there too, in more iterations.
    rj, ij = solve(W, q, mu, tol=1e-6, max_iterations=20000, method="jacobi")
    _report("jacobi dense", ij, 300)
    assert ij.converged and natural_map(W, q, mu, rj) <= 1e-6 and ij.iterations > info.iterations
    # Warm-started from its own solution, Gauss-Seidel has nothing left to do.
    _, iw = solve(W, q, mu, r0=r)
    assert iw.iterations == 0 and iw.converged


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_anderson_matches_plain_gauss_seidel(solve, mu):
    """Anderson-accelerated sweeps reach the plain sweeps' solution (an independent residual, and
    an LCP by enumeration when frictionless), in fewer sweeps on a strongly coupled soft body."""
    rng = np.random.default_rng(3)
    W, q, _ = soft_body_problem(60 if mu else 8, 200, rng)
    plain, ip = solve(W, q, mu, tol=1e-10, max_iterations=20000, anderson=0)
    fast, ia = solve(W, q, mu, tol=1e-10, max_iterations=20000)
    assert ip.converged and ia.converged and natural_map(W, q, mu, fast) <= 1e-10
    np.testing.assert_allclose(fast, plain, atol=1e-7 * np.abs(plain).max())
    if mu == 0:
        np.testing.assert_allclose(fast[0::3], lcp_by_enumeration(W[0::3, 0::3], q[0::3]), atol=1e-8)
    else:
        assert ia.iterations < ip.iterations


@pytest.mark.parametrize("method", ["gauss_seidel", "jacobi"])
def test_rigid_bodies_sparse_csr_matches_dense(solve, method):
    from tissue.contact import FrictionalContactSolver
    W, q, mu = rigid_bodies_problem(120, 300, np.random.default_rng(1))
    s = FrictionalContactSolver(W, mu, method=method)
    assert not s.dense                                    # large and sparse: block-CSR
    tol, cap = (1e-6, 5000) if method == "gauss_seidel" else (1e-4, 20000)
    r, info = s.solve(q, tol=tol, max_iterations=cap)
    _report(f"{method} block-CSR (rigid bodies)", info, 300)
    assert info.converged and natural_map(W, q, mu, r) <= tol
    rd, idn = solve(W.toarray(), q, mu, tol=tol, max_iterations=cap, method=method)
    assert abs(idn.iterations - info.iterations) <= 2     # same algorithm, rounding aside
    np.testing.assert_allclose(rd, r, atol=1e-6)
    # A dense W may be asked to go to block-CSR too (its zero blocks dropped).
    rc, ic = solve(W.toarray(), q, mu, tol=tol, max_iterations=cap, method=method, layout="csr")
    assert ic.iterations == info.iterations and np.array_equal(rc, r)


def two_body_factored_problem(nc, nnodes, rng, h=0.04):
    """Contacts of soft body 0 against rigid ground or a triangle of soft body 1, as the contact
    stage poses them with compliance warping: W = Σ_b H_b C_b H_bᵀ (dense here, from the two bodies'
    compliances), and the same W as a FactoredDelassus (C_b restricted to the nodes H_b touches)."""
    from tissue.contact import FactoredDelassus

    _, _, mu = soft_body_problem(nc, nnodes, rng, h)
    C = []
    for _ in range(2):                                   # two bodies' compliances, as soft_body_problem's
        A = rng.standard_normal((3 * nnodes, 3 * nnodes))
        C.append(h * np.linalg.inv(np.eye(3 * nnodes) + 0.02 * A @ A.T))
    H = [np.zeros((3 * nc, 3 * nnodes)) for _ in range(2)]
    blocks = []                                          # (contact, body, node, 3×3 block)
    for c in range(nc):
        F = frame(rng.standard_normal(3))
        for body, sign in ((0, 1.0), (1, -1.0)) if c % 3 == 0 else ((0, 1.0),):
            for node, w in zip(rng.choice(nnodes, 3, replace=False), rng.dirichlet(np.ones(3))):
                H[body][3 * c:3 * c + 3, 3 * node:3 * node + 3] += sign * w * F
                blocks.append((c, body, node, sign * w * F))
    W = sum(Hb @ Cb @ Hb.T for Hb, Cb in zip(H, C))
    touched = [np.unique([n for _, b, n, _ in blocks if b == body]) for body in range(2)]
    d = np.array([3 * len(t) for t in touched])
    y_offset, q_offset = np.r_[0, np.cumsum(d)], np.r_[0, np.cumsum(d ** 2)][:-1]
    dofs = [(3 * t[:, None] + np.arange(3)).ravel() for t in touched]
    Q = np.concatenate([Cb[np.ix_(k, k)].ravel() for Cb, k in zip(C, dofs)])
    col = [y_offset[b] + 3 * int(np.searchsorted(touched[b], n)) for _, b, n, _ in blocks]
    ptr = np.r_[0, np.cumsum(np.bincount([c for c, *_ in blocks], minlength=nc))]
    diagonal = W.reshape(nc, 3, nc, 3)[np.arange(nc), :, np.arange(nc), :].copy()
    F = FactoredDelassus(ptr, np.array(col), np.array([b for _, b, _, _ in blocks]),
                         np.array([B for *_, B in blocks]), Q, y_offset, q_offset, diagonal)
    q = np.column_stack([rng.uniform(-1, 0.3, nc), 0.5 * rng.standard_normal((nc, 2))]).ravel()
    scale = np.mean(np.diagonal(W))
    return W / scale, F.scaled(1 / scale), q, mu


@pytest.mark.parametrize("mu", [0.0, 0.4])
def test_anderson_over_the_contacts_that_carry_reactions(solve, mu):
    """Anderson's history is kept for the contacts that have carried a reaction in the launch alone
    (listed in the problem's `carried`, in order): on a factored two-body problem where most
    contacts separate, warm-started on a few and reaching the others' reactions sweep by sweep,
    the solution is the plain sweeps' and, frictionless, the QP's (scipy, independent), to the
    tolerance; the list holds, once each and ascending, every contact that ends with a reaction.
    The same solver then re-solves other q (as the haptic loop does): the history and the list a
    solve leaves behind must not reach the next (a contact joining has its history zeroed, the
    list is built anew at the launch's start), so sweeps and r equal a fresh solver's bit for bit
    (test_renewed_solver_equals_fresh_solvers checks the same across problems)."""
    from tissue.contact import FrictionalContactSolver

    rng = np.random.default_rng(8)
    W, F, q, _ = two_body_factored_problem(80, 50, rng)
    q[0::3] = np.where(rng.random(80) < 0.25, -rng.random(80), 0.2 + rng.random(80))   # most apart
    r0 = np.zeros(240)
    r0[0:15:3] = 0.1                                        # a warm start on five contacts
    fast = FrictionalContactSolver(F, mu, "gauss_seidel", check=False)
    r, info = fast.solve(q, 1e-11, 20000, r0=r0)
    plain, info_p = solve(W, q, mu, tol=1e-11, max_iterations=20000, r0=r0, anderson=0)
    assert info.converged and info_p.converged and natural_map(W, q, mu, r) <= 1e-11
    np.testing.assert_allclose(r, plain, atol=1e-8 * np.abs(plain).max())
    carried = fast.storage.get("carried", 1, None)
    room = (len(carried) - 1) // 2
    listed = carried[room:room + carried[2 * room]]
    pushed = np.flatnonzero(r.reshape(-1, 3).any(axis=1))
    assert np.all(np.diff(listed) > 0) and np.isin(pushed, listed).all() and len(listed) < 80
    assert np.array_equal(np.flatnonzero(carried[:80]), listed)
    if mu == 0:
        Wn, qn = W[0::3, 0::3], q[0::3]
        qp = scipy.optimize.minimize(lambda x: (0.5 * x @ Wn @ x + qn @ x, Wn @ x + qn), np.zeros(80), jac=True,
                                     method="L-BFGS-B", bounds=[(0, None)] * 80,
                                     options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000})
        np.testing.assert_allclose(r[0::3], qp.x, atol=1e-6 * np.abs(qp.x).max())
    for k in range(5):
        q_next = q.copy()
        q_next[0::3] = np.where(rng.random(80) < 0.25, -rng.random(80), 0.2 + rng.random(80))
        again, info_a = fast.solve(q_next, 1e-11, 20000, r0=r0 if k % 2 else None)
        fresh, info_f = FrictionalContactSolver(F, mu, "gauss_seidel", check=False).solve(
            q_next, 1e-11, 20000, r0=r0 if k % 2 else None)
        assert info_a.converged and (info_a.iterations, info_a.residual) == (info_f.iterations, info_f.residual), k
        np.testing.assert_array_equal(again, fresh, err_msg=f"re-solve {k}")


@pytest.mark.parametrize("method", ["gauss_seidel", "jacobi"])
def test_factored_delassus_matches_dense(solve, method):
    """The factored layout (W = Σ P Q Pᵀ, never formed) against the dense W built here from the
    same bodies: the operator itself, and the solution of the same problem by each layout."""
    W, F, q, mu = two_body_factored_problem(90, 60, np.random.default_rng(4))
    assert np.linalg.norm(F.toarray() - W) <= 1e-12 * np.linalg.norm(W)
    r = np.random.default_rng(5).standard_normal(len(q))
    np.testing.assert_allclose(F @ r, W @ r, atol=1e-12 * np.abs(W @ r).max())
    tol, cap = (1e-8, 5000) if method == "gauss_seidel" else (1e-5, 50000)
    rf, info = solve(F, q, mu, tol=tol, max_iterations=cap, method=method)
    rd, idn = solve(W, q, mu, tol=tol, max_iterations=cap, method=method)
    _report(f"{method} factored", info, len(mu))
    assert info.converged and natural_map(W, q, mu, rf) <= tol
    assert abs(idn.iterations - info.iterations) <= 2     # same algorithm, rounding aside
    np.testing.assert_allclose(rf, rd, atol=10 * tol * (1 + np.linalg.norm(q)))


@pytest.mark.parametrize("room", [64, 16, 0])
def test_factored_sweeps_in_play_match_dense(backend, monkeypatch, room):
    """The factored layout's sweeps that pass over the contacts apart read W formed among the
    contacts in play (up to IN_PLAY_MAX of them; beyond that room, or with none, y through the
    factors): the same sweeps as on the dense W built from the bodies, rounding aside, on a problem
    where few contacts touch (17 come into play here: room for 16 runs out mid-solve). Those sweeps
    visit the contacts in play in the order every sweep does (listed ascending after the slots')."""
    from tissue.contact import frictional_contact
    from tissue.contact.frictional_contact import FrictionalContactSolver

    monkeypatch.setattr(frictional_contact, "IN_PLAY_MAX", room)
    W, F, q, mu = two_body_factored_problem(90, 60, np.random.default_rng(6))
    q = q.reshape(-1, 3)
    q[:, 0] = np.random.default_rng(7).uniform(-0.2, 1.0, len(q))
    q = q.ravel()
    tol, n = 1e-8, len(mu)
    factored = FrictionalContactSolver(F, mu, "gauss_seidel", check=False)
    rf, info = factored.solve(q, tol, 5000)
    rd, idn = FrictionalContactSolver(W, mu, "gauss_seidel", check=False).solve(q, tol, 5000)
    active = factored.storage._arrays["active"]
    in_play = int(active[n + min(n, room)]) if room else 0
    _report(f"factored, room {room} ({in_play} formed)", info, n)
    assert in_play == {64: 17, 16: 16, 0: 0}[room]
    slots, ascending = active[n:n + in_play], active[n + min(n, room) + 1:][:in_play]
    assert np.array_equal(ascending, np.sort(slots)) and len(set(slots)) == in_play
    assert info.iterations > 2 * 8                 # (sweeps over all contacts among them)
    assert info.converged and natural_map(W, q, mu, rf) <= tol
    assert abs(idn.iterations - info.iterations) <= 2
    np.testing.assert_allclose(rf, rd, atol=10 * tol * (1 + np.linalg.norm(q)))


def test_newton_reads_W_among_the_contacts_in_play_the_sweeps_formed(backend):
    """Newton's blocks of a factored W (its closing contacts are in play) come from W among the
    contacts in play that the sweeps before it formed, where that holds them all, else from the
    factors: both equal the dense W built from the bodies; a renewed problem's are not reused."""
    from tissue.contact.frictional_contact import FrictionalContactSolver

    W, F, q, mu = two_body_factored_problem(90, 60, np.random.default_rng(6))
    q = q.reshape(-1, 3)
    q[:, 0] = np.random.default_rng(7).uniform(-0.2, 1.0, len(q))
    q = q.ravel()
    solver = FrictionalContactSolver(F, mu, "gauss_seidel", check=False)
    assert solver._formed_block(np.arange(2), np.arange(2)) is None        # no sweeps yet
    r, _ = solver.solve(q, 1e-8, 5000)
    play = np.flatnonzero((r.reshape(-1, 3) != 0).any(axis=1))
    rows, cols = play[::-1], play[::2]
    apart = np.setdiff1d(np.arange(len(mu)), play)[:3]
    dofs = lambda c: (3 * c[:, None] + np.arange(3)).ravel()
    assert solver._formed_block(rows, cols) is not None
    assert solver._formed_block(np.r_[rows, apart], cols) is None
    for a, b in ((rows, cols), (rows, rows), (np.r_[rows, apart], cols)):
        np.testing.assert_allclose(solver._block(a, b), W[np.ix_(dofs(a), dofs(b))], rtol=0,
                                   atol=1e-12 * np.abs(W).max())
    solver.renew(F, mu)
    assert solver._formed_block(rows, cols) is None


def test_factored_blocks_equal_the_formed_W(solve):
    """FactoredDelassus.block between sets of contacts (unsorted, overlapping, one contact, all)
    from one operator, whose P is built at the first call and reused: W formed here among them
    (within 1e-12 of its largest entry), and the same bits as a new operator of the same factors
    serving that block first."""
    from dataclasses import replace

    rng = np.random.default_rng(8)
    W, F, q, mu = two_body_factored_problem(60, 40, rng)
    dofs = lambda c: (3 * np.asarray(c)[:, None] + np.arange(3)).ravel()
    sets = [rng.choice(60, 25, replace=False), rng.choice(60, 40, replace=False), np.array([7]), np.arange(60)]
    for rows in sets:
        for cols in sets:
            B = F.block(rows, cols)
            np.testing.assert_allclose(B, W[np.ix_(dofs(rows), dofs(cols))], rtol=0, atol=1e-12 * np.abs(W).max())
            assert replace(F).block(rows, cols).tobytes() == B.tobytes()


@pytest.mark.parametrize("layout", ["factored", "dense"])
def test_contacts_in_play_solve_the_whole_problem(solve, layout):
    """Most contacts apart (q_n > 0), as within an alarm distance: Gauss-Seidel on the contacts in
    play (W among them formed from the factors) against sweeps over the whole problem, and
    against W formed here: the same solution, an independent residual ≤ tol, apart contacts
    carrying nothing."""
    from tissue.contact import FrictionalContactSolver

    rng = np.random.default_rng(6)
    W, F, q, mu = two_body_factored_problem(150, 80, rng)
    q[0::3] = np.where(rng.random(150) < 0.12, -rng.random(150), 0.05 + rng.random(150))
    idx = np.flatnonzero(rng.random(150) < 0.2)
    dofs = (3 * idx[:, None] + np.arange(3)).ravel()
    assert np.linalg.norm(F.restricted(idx) - W[np.ix_(dofs, dofs)]) <= 1e-12 * np.linalg.norm(W)
    op = F if layout == "factored" else W
    tol = 1e-9
    results = {}
    for reduce in (True, False):
        r, info = FrictionalContactSolver(op, mu, reduce=reduce).solve(q, tol=tol, max_iterations=5000)
        assert info.converged and natural_map(W, q, mu, r) <= tol
        results[reduce] = r
    np.testing.assert_allclose(results[True], results[False], atol=10 * tol * (1 + np.linalg.norm(q)))
    apart = (W @ results[True] + q)[0::3] > 1e-9
    assert apart.sum() > 100 and np.all(results[True].reshape(-1, 3)[apart] == 0)


@pytest.mark.parametrize("layout, method, reduce", [("factored", "auto", False), ("dense", "auto", False),
                                                    ("dense", "gauss_seidel", True), ("factored", "newton", False),
                                                    ("csr", "gauss_seidel", False), ("factored", "jacobi", False)])
def test_kept_storage_equals_fresh_solvers(solve, layout, method, reduce):
    """Solvers made one after the other on one kept Storage (as the contact stage does each step:
    capacity-sized arrays that hold the previous, larger problems' data past the current one's
    end, argpacks built once per capacity, the sweeps' launch replayed) against a fresh solver per
    problem (arrays of its own, every argpack new, launched through Taichi): problems of 40, 90,
    25, 150 and 60 contacts, most apart, warm-started or not. Reactions, velocities, iterations
    and residual equal bit for bit; a smaller problem after a larger one reuses the argpacks."""
    from tissue.contact import FrictionalContactSolver
    from tissue.contact.storage import Storage

    rng = np.random.default_rng(11)
    kept = Storage(host=True)
    packs = []
    for k, nc in enumerate((40, 90, 25, 150, 60)):
        W, F, q, mu = two_body_factored_problem(nc, nc // 2 + 10, rng)
        q[0::3] = np.where(rng.random(nc) < 0.3, -rng.random(nc), 0.05 + rng.random(nc))
        op = {"factored": F, "dense": W, "csr": sp.csr_matrix(W)}[layout]
        rn = rng.random(nc)                                  # a start inside the cones
        r0 = np.column_stack([rn, 0.3 * (mu * rn)[:, None] * rng.uniform(-1, 1, (nc, 2))]).ravel() if k % 2 else None
        out = []
        for storage in (kept, None):
            solver = FrictionalContactSolver(op, mu, method, layout="csr" if layout == "csr" else "auto",
                                             reduce=reduce, storage=storage)
            r, info = solver.solve(q, tol=1e-8, max_iterations=3000, r0=r0)
            out.append((r, solver.u, info.iterations, info.residual))
            if storage is kept:
                packs.append((solver._W, solver._P))
        (r, u, its, res), (r_f, u_f, its_f, res_f) = out
        assert info.converged, (nc, info)
        np.testing.assert_array_equal(r, r_f, err_msg=f"{nc} contacts: r")
        np.testing.assert_array_equal(u, u_f, err_msg=f"{nc} contacts: u")
        assert (its, res) == (its_f, res_f), nc
    assert packs[2][0] is packs[1][0] and packs[2][1] is packs[1][1]     # 25 after 90: no growth


@pytest.mark.parametrize("method, reduce", [("auto", False), ("gauss_seidel", True), ("jacobi", False)])
def test_renewed_solver_equals_fresh_solvers(solve, method, reduce):
    """One solver renewed from problem to problem (as the contact stage keeps one a run) against a
    fresh solver per problem: 40, 90 contacts, 90 again (other W, q and μ: its sizes are not
    written again), 25, 150 and 60, factored and dense in turn, warm-started or not; before the
    third, another solver solves a problem of 70 contacts on the same storage (so the renewed one
    writes its sizes again). Reactions, velocities, iterations and residual equal bit for bit."""
    from tissue.contact import FrictionalContactSolver
    from tissue.contact.storage import Storage

    rng = np.random.default_rng(12)
    kept, renewed = Storage(host=True), None
    for k, nc in enumerate((40, 90, 90, 25, 150, 60)):
        W, F, q, mu = two_body_factored_problem(nc, nc // 2 + 10, rng)
        q[0::3] = np.where(rng.random(nc) < 0.3, -rng.random(nc), 0.05 + rng.random(nc))
        op = F if k % 2 == 0 else W
        rn = rng.random(nc)                                  # a start inside the cones
        r0 = np.column_stack([rn, 0.3 * (mu * rn)[:, None] * rng.uniform(-1, 1, (nc, 2))]).ravel() if k % 3 else None
        if k == 2:
            W2, _, q2, mu2 = two_body_factored_problem(70, 45, rng)
            FrictionalContactSolver(W2, mu2, method, reduce=reduce, storage=kept).solve(q2, 1e-8, 3000)
        if renewed is None:
            renewed = FrictionalContactSolver(op, mu, method, reduce=reduce, storage=kept)
        else:
            assert renewed.renew(op, mu, reduce) is renewed
        fresh = FrictionalContactSolver(op, mu, method, reduce=reduce)
        tol, cap = (1e-8, 3000) if method != "jacobi" else (1e-5, 50000)
        r, info = renewed.solve(q, tol, cap, r0=r0)
        r_f, info_f = fresh.solve(q, tol, cap, r0=r0)
        assert info.converged, (nc, info)
        np.testing.assert_array_equal(r, r_f, err_msg=f"{nc} contacts: r")
        np.testing.assert_array_equal(renewed.u, fresh.u, err_msg=f"{nc} contacts: u")
        assert (info.iterations, info.residual) == (info_f.iterations, info_f.residual), nc


def test_jacobi_safeguard_recovers_from_too_large_omega(solve):
    from tissue.contact import FrictionalContactSolver
    W, q, mu = rigid_bodies_problem(3, 30, np.random.default_rng(0))   # strongly coupled contacts
    s = FrictionalContactSolver(W, mu, method="jacobi", omega=1.0)
    r, info = s.solve(q, tol=1e-6, max_iterations=20000)
    assert info.converged and natural_map(W, q, mu, r) <= 1e-6 and s.last_omega < 1.0


# ----------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------

def _bad_cases():
    W = np.eye(6)
    q = np.array([-1.0, 0, 0, -1, 0, 0])
    nonpd = np.eye(6)
    nonpd[3, 3] = 0.0
    missing = sp.csr_matrix(np.kron(np.array([[0, 1], [1, 0]]), np.ones((3, 3))) + 0.0)
    return [
        (dict(W=np.ones((6, 3)), q=q, mu=0.1), "W: must be square"),
        (dict(W=np.eye(5), q=q[:5], mu=0.1), "W: size must be 3"),
        (dict(W=W, q=q[:3], mu=0.1), "q: expected shape (6,)"),
        (dict(W=W, q=q, mu=[0.1, 0.2, 0.3]), "mu: expected a scalar or shape (2,)"),
        (dict(W=W, q=q, mu=[0.1, -0.2]), "mu: negative friction coefficient at contact 1"),
        (dict(W=np.where(np.eye(6) > 0, np.nan, 0), q=q, mu=0.1), "W: contains non-finite"),
        (dict(W=W, q=np.r_[q[:5], np.inf], mu=0.1), "q: contains non-finite"),
        (dict(W=W, q=q, mu=[0.1, np.nan]), "mu: contains non-finite"),
        (dict(W=W, q=q, mu=0.1, r0=np.zeros(3)), "r0: expected shape (6,)"),
        (dict(W=W, q=q, mu=0.1, r0=np.full(6, np.nan)), "r0: contains non-finite"),
        (dict(W=nonpd, q=q, mu=0.1), "W: diagonal 3x3 block of contact 1 is not positive definite"),
        (dict(W=missing, q=q, mu=0.1), "W: diagonal 3x3 block of contact 0 is not positive definite"),
        (dict(W=W, q=q, mu=0.1, method="lemke"), "method: unknown value 'lemke'; expected one of gauss_seidel, jacobi, newton, auto"),
        (dict(W=W, q=q, mu=0.1, tol=-1.0), "tol: must be a positive number"),
    ]


@pytest.mark.parametrize("kwargs, message", _bad_cases())
def test_bad_input(solve, kwargs, message):
    with pytest.raises(TissueError) as e:
        solve(**kwargs)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_no_contacts(solve):
    r, info = solve(np.zeros((0, 0)), np.zeros(0), 0.3)
    assert r.shape == (0,) and info.converged and info.iterations == 0


# ----------------------------------------------------------------------------------------------
# semi-smooth Newton (tissue.contact.newton) and "auto" (Gauss-Seidel, then Newton)
# ----------------------------------------------------------------------------------------------

def test_alart_curnier_jacobian_matches_finite_differences():
    """dΦ = A dr + B W dr against central differences of Φ(r, W r + q), at random points off the
    kinks (closing and separating, sticking and sliding contacts all present)."""
    from tissue.contact.newton import _alart_curnier

    rng = np.random.default_rng(11)
    n = 40
    W = random_delassus(n, rng)
    r = np.column_stack([rng.uniform(-0.5, 1.5, n), rng.standard_normal((n, 2))]).ravel()
    q = rng.standard_normal(3 * n)
    # A third of the contacts nearly at rest tangentially with a small r_t: they stick.
    calm = np.arange(0, n, 3)
    r.reshape(n, 3)[calm, 0] = rng.uniform(0.5, 1.5, len(calm))
    r.reshape(n, 3)[calm, 1:] = 0.01 * rng.standard_normal((len(calm), 2))
    q.reshape(n, 3)[calm, 1:] = -(W @ r).reshape(n, 3)[calm, 1:] + 1e-3 * rng.standard_normal((len(calm), 2))
    mu = rng.uniform(0.3, 1.0, n)
    rho = rng.uniform(0.5, 2.0, n)[:, None] * np.array([1.0, 1.3, 1.3])   # (ρ_n, ρ_t, ρ_t), apart: newton._rho's form

    def phi(r):
        return _alart_curnier(r.reshape(n, 3), (W @ r + q).reshape(n, 3), mu, rho, jacobian=False)[0].ravel()

    _, A, B = _alart_curnier(r.reshape(n, 3), (W @ r + q).reshape(n, 3), mu, rho)
    kinds = set()
    for k in range(5):
        d = rng.standard_normal(3 * n)
        eps = 1e-7
        fd = (phi(r + eps * d) - phi(r - eps * d)) / (2 * eps)
        jac = np.einsum("iab,ib->ia", A, d.reshape(n, 3)) + np.einsum("iab,ib->ia", B, (W @ d).reshape(n, 3))
        np.testing.assert_allclose(jac.ravel(), fd, atol=1e-6 * np.abs(fd).max())
    closing = (r.reshape(n, 3)[:, 0] - rho[:, 0] * (W @ r + q).reshape(n, 3)[:, 0]) > 0
    stick = closing & (A[:, 1, 1] == 0)
    assert closing.sum() > 5 and (~closing).sum() > 5 and stick.sum() > 0 and (closing & ~stick).sum() > 5


@pytest.mark.parametrize("method", ["newton", "auto"])
def test_newton_single_contact_closed_form(solve, method):
    # As test_single_contact_stick_slide_separate: r_n = -q_n / w_n; stick r_t = -q_t / w_t,
    # slide r_t = -mu r_n q_t / |q_t|; separating r = 0.
    wn, wt, mu = 2.0, 0.5, 0.4
    W = np.diag([wn, wt, wt])
    rn = 1.5
    for qt, sticks in (([0.1, -0.2], True), ([0.8, 0.6], False)):
        qt = np.array(qt)
        r, info = solve(W, np.r_[-wn * rn, qt], mu, tol=1e-14, method=method)
        expect_t = -qt / wt if sticks else -mu * rn * qt / np.linalg.norm(qt)
        np.testing.assert_allclose(r, np.r_[rn, expect_t], rtol=1e-12, atol=1e-14)
        assert info.converged and info.method == method
    r, info = solve(W, np.array([0.3, 5.0, -1.0]), mu, method=method)
    assert np.all(r == 0) and info.iterations == 0


@pytest.mark.parametrize("seed", range(6))
def test_newton_frictionless_matches_enumeration_and_qp(solve, seed):
    rng = np.random.default_rng(100 + seed)
    n = 2 + seed
    W = random_delassus(n, rng)
    q = rng.standard_normal(3 * n)
    r, info = solve(W, q, 0.0, tol=1e-12, max_iterations=100, method="newton")
    assert info.converged and natural_map(W, q, 0.0, r) <= 1e-12
    Wn, qn = W[0::3, 0::3], q[0::3]
    np.testing.assert_allclose(r[0::3], lcp_by_enumeration(Wn, qn), atol=1e-9)
    qp = scipy.optimize.minimize(lambda x: (0.5 * x @ Wn @ x + qn @ x, Wn @ x + qn), np.zeros(n), jac=True,
                                 method="L-BFGS-B", bounds=[(0, None)] * n,
                                 options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000})
    np.testing.assert_allclose(r[0::3], qp.x, atol=1e-6)


def box_stack(boxes, h=0.01, g=9.81, mu=0.5):
    """A column of unit boxes (mass 1) at rest on the ground, 4 corner contacts under each: 12 rows
    per 6 dofs, W = J M⁻¹ Jᵀ singular. Returns W, q (one step of gravity), mu, J, M⁻¹, v_free."""
    inertia = 1.0 / 12 * 2.0                              # (1² + 1²) / 12 for a unit cube
    Minv = np.diag(np.tile(np.r_[np.ones(3), np.full(3, 1 / inertia)], boxes))
    J = np.zeros((12 * boxes, 6 * boxes))
    for b in range(boxes):
        for k, (sx, sy) in enumerate(itertools.product((-0.5, 0.5), repeat=2)):
            arm = np.array([sx, sy, -0.5])                # the corner, from the box's centre
            F = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]])    # (normal z; tangents x, y)
            row = 3 * (4 * b + k)
            J[row:row + 3, 6 * b:6 * b + 6] = np.hstack([F, -F @ skew(arm)])
            if b > 0:                                     # the box below: the same point, from its centre
                J[row:row + 3, 6 * (b - 1):6 * b] = -np.hstack([F, -F @ skew(arm + [0, 0, 1.0])])
    v = np.zeros(6 * boxes)
    v[2::6] = -h * g
    return J @ Minv @ J.T, J @ v, mu, J, Minv, v


@pytest.mark.parametrize("method", ["newton", "auto"])
def test_newton_rigid_stack_comes_to_rest(solve, method):
    """A stack of 6 boxes (72 rows, 36 dofs): every box at rest after the step and the ground
    carrying the whole weight, h m g × 6; projected Gauss-Seidel stalls on it (singular W)."""
    h, g, boxes = 0.01, 9.81, 6
    W, q, mu, J, Minv, v = box_stack(boxes, h, g)
    r, info = solve(W, q, mu, tol=1e-10, max_iterations=200, method=method)
    assert info.converged and natural_map(W, q, mu, r) <= 1e-10
    np.testing.assert_allclose(v + Minv @ J.T @ r, 0.0, atol=1e-8)
    assert r[0:12:3].sum() == pytest.approx(boxes * h * g, rel=1e-8)
    _, gs = solve(W, q, mu, tol=1e-10, max_iterations=500)
    assert not gs.converged                               # why Newton is there


def solvable_problem(W, mu, rng):
    """q for which a known r* solves (W, q, mu): per contact separated (r* = 0, u_n > 0),
    sticking (u = 0, r* inside the cone) or sliding (u_n = 0, r*_t = -mu r*_n u_t / |u_t|);
    q = u* - W r*. (Random q are often infeasible when rows outnumber the dofs.)"""
    n = len(mu)
    R, U = np.zeros((n, 3)), np.zeros((n, 3))
    kind = rng.integers(3, size=n)
    sep, stick, slide = kind == 0, kind == 1, kind == 2
    U[sep, 0] = rng.uniform(0.1, 1.0, sep.sum())
    R[stick, 0] = rng.uniform(0.5, 1.5, stick.sum())
    angle = rng.uniform(0, 2 * np.pi, n)
    R[stick, 1:] = (0.5 * mu * R[:, 0])[stick, None] * np.column_stack([np.cos(angle), np.sin(angle)])[stick]
    R[slide, 0] = rng.uniform(0.5, 1.5, slide.sum())
    direction = np.column_stack([np.cos(angle), np.sin(angle)])[slide]
    U[slide, 1:] = rng.uniform(0.1, 1.0, (slide.sum(), 1)) * direction
    R[slide, 1:] = -(mu * R[:, 0])[slide, None] * direction
    return U.ravel() - W @ R.ravel(), R.ravel()


@pytest.mark.parametrize("method", ["newton", "auto"])
def test_newton_soft_body_more_rows_than_dofs(solve, method, monkeypatch):
    """300 contacts on a soft body of 60 nodes (900 rows, 180 dofs: W singular), from zero and
    warm-started from a nearby problem's solution, which takes fewer Newton steps (auto's
    iterations count sweeps and Newton steps together: warm, it ends within its sweeps); the
    residual recomputed here."""
    from tissue.contact import newton

    steps, newton_step = [], newton.newton_step
    # steps: each Newton step's system size (3 × the closing contacts, newton_step's `closing`)
    monkeypatch.setattr(newton, "newton_step",
                        lambda *a, **k: steps.append(3 * np.count_nonzero(a[6])) or newton_step(*a, **k))
    rng = np.random.default_rng(7)
    W, _, mu = soft_body_problem(300, 60, rng)
    W /= np.mean(np.diagonal(W))                          # as the contact stage poses it
    q, r_star = solvable_problem(W, mu, rng)
    assert natural_map(W, q, mu, r_star) < 1e-12
    r, info = solve(W, q, mu, tol=1e-9, max_iterations=300, method=method)
    cold = len(steps)
    assert info.converged and natural_map(W, q, mu, r) <= 1e-9 and cold > 0
    R, slack = r.reshape(-1, 3), 1e-9 * (1 + np.linalg.norm(q))      # (the residual's scale)
    assert np.all(R[:, 0] >= -slack) and np.all(np.hypot(R[:, 1], R[:, 2]) <= mu * R[:, 0] + slack)
    # Warm-started on a nearby problem, solvable for sure (the cone conditions scale: 1.05 r*).
    r2, warm = solve(W, 1.05 * q, mu, tol=1e-9, max_iterations=300, method=method, r0=r)
    assert warm.converged and natural_map(W, 1.05 * q, mu, r2) <= 1e-9 and len(steps) - cold < cold


@pytest.mark.parametrize("eps", [1e-3, 1e-2])
def test_newton_proximal_points_solve_the_true_problem(solve, monkeypatch, eps):
    """Newton's proximal points (newton.CRAWL = 1: from the first step on) on a singular
    soft-body problem (60 contacts on 15 nodes: 180 rows, 45 dofs): steps on (W + εI, q - ε r_k), the anchor r_k moving,
    end at a solution of the true problem: its natural-map residual, recomputed here with W (not
    W + εI), ≤ 1e-9, where the regularised problem's own solution is off by about ε |r|."""
    from tissue.contact import newton

    steps, newton_step = [], newton.newton_step
    monkeypatch.setattr(newton, "newton_step", lambda W, *a, **k: steps.append(W is None) or newton_step(W, *a, **k))
    monkeypatch.setattr(newton, "CRAWL", 1.0)
    monkeypatch.setattr(newton, "PROXIMAL", eps)
    rng = np.random.default_rng(7)
    W, _, mu = soft_body_problem(60, 15, rng)
    W /= np.mean(np.diagonal(W))
    q, _ = solvable_problem(W, mu, rng)
    r, info = solve(W, q, mu, tol=1e-9, max_iterations=300, method="newton")
    assert info.converged and natural_map(W, q, mu, r) <= 1e-9 and steps and all(steps)
    # The regularised problem (W + εI, q) alone, an anchor that never moves: off the true one.
    r_eps, _ = solve(W + eps * np.eye(len(q)), q, mu, tol=1e-11, max_iterations=300, method="newton")
    assert natural_map(W, q, mu, r_eps) > 1e3 * 1e-9


def test_newton_factored_and_sparse_match_dense(solve):
    """The same problem with W dense, block-sparse and as its factors: the same reactions."""
    rng = np.random.default_rng(5)
    Wd, Wf, q, mu = two_body_factored_problem(40, 30, rng)
    rd, id_ = solve(Wd, q, mu, tol=1e-11, max_iterations=100, method="newton")
    rf, if_ = solve(Wf, q, mu, tol=1e-11, max_iterations=100, method="newton")
    rs, is_ = solve(sp.csr_matrix(Wd), q, mu, tol=1e-11, max_iterations=100, method="newton")
    assert id_.converged and if_.converged and is_.converged
    for r in (rd, rf, rs):
        assert natural_map(Wd, q, mu, r) <= 1e-11
    np.testing.assert_allclose(rf, rd, atol=1e-8 * np.abs(rd).max())


def test_auto_equals_gauss_seidel_where_the_sweeps_converge(solve):
    """auto's sweeps are Gauss-Seidel's own launch: on a problem they finish, the same sweeps and
    the same reactions; on the rigid stack (singular W) they stall within AUTO_SWEEPS and Newton
    finishes."""
    from tissue.contact.frictional_contact import AUTO_SWEEPS

    rng = np.random.default_rng(11)
    W = random_delassus(40, rng)
    q = np.column_stack([rng.uniform(-1, 0.5, 40), rng.standard_normal((40, 2))]).ravel()
    ra, auto = solve(W, q, 0.4, tol=1e-8, max_iterations=AUTO_SWEEPS, method="auto")
    rg, gs = solve(W, q, 0.4, tol=1e-8, max_iterations=AUTO_SWEEPS, method="gauss_seidel")
    assert gs.converged and auto.iterations == gs.iterations
    np.testing.assert_array_equal(ra, rg)
    W, q, mu, *_ = box_stack(6, 0.01, 9.81)
    r, info = solve(W, q, mu, tol=1e-10, max_iterations=200, method="auto")
    assert info.converged and natural_map(W, q, mu, r) <= 1e-10


def test_auto_sweeps_small_problems_longer(solve, monkeypatch):
    """Below AUTO_SMALL contacts a sweep costs microseconds and Newton's host step far more, so
    auto sweeps on while every AUTO_PHASE_SMALL sweeps halve the residual at a rate that reaches
    the tolerance within AUTO_SWEEPS_SMALL: 11 contacts on 3 rigid boxes, which Gauss-Seidel
    finishes in 114 sweeps (at the rate of its first 16, not within AUTO_HORIZON), end in the
    sweeps, as Gauss-Seidel's; with the rule of larger problems Newton finishes them."""
    from tissue.contact import frictional_contact, newton

    steps, newton_step = [], newton.newton_step
    monkeypatch.setattr(newton, "newton_step", lambda *a, **k: steps.append(1) or newton_step(*a, **k))
    W, q, mu = rigid_bodies_problem(3, 11, np.random.default_rng(143))
    W = W.toarray()
    rg, gs = solve(W, q, mu, tol=1e-8, max_iterations=1000, method="gauss_seidel")
    ra, auto = solve(W, q, mu, tol=1e-8, max_iterations=1000, method="auto")
    assert gs.converged and gs.iterations == 114 and auto.iterations == gs.iterations and not steps
    np.testing.assert_array_equal(ra, rg)
    monkeypatch.setattr(frictional_contact, "AUTO_SMALL", 0)
    rn, larger = solve(W, q, mu, tol=1e-8, max_iterations=1000, method="auto")
    assert steps and larger.converged and natural_map(W, q, mu, rn) <= 1e-8


def test_newton_gmres_on_a_nearby_factor_matches_lapack():
    """_gmres: a system whose rows differ from the factorised one's in a few places (as a Newton
    system after a few contacts changed state), and one among partly other contacts (some opened,
    some closed), solved to the tolerance, checked against numpy's float64 solve; on an unrelated
    matrix it reports failure (None) instead of a poor x."""
    import scipy.linalg

    from tissue.contact.newton import _gmres, _preconditioner

    rng = np.random.default_rng(31)
    k = 702  # 234 contacts
    J0 = np.eye(k) + rng.standard_normal((k, k)) / (3 * np.sqrt(k))
    lu = scipy.linalg.lu_factor(J0.astype(np.float32))
    J = J0 + 1e-3 * rng.standard_normal((k, k)) / np.sqrt(k)
    J[rng.choice(k, 6, replace=False)] += rng.standard_normal((6, k)) / np.sqrt(k)     # rows changed
    b = rng.standard_normal(k)
    x = _gmres(J, b, _preconditioner(J, lu, np.arange(k // 3), np.arange(k // 3)), 1e-10, 30)
    reference = np.linalg.solve(J, b)
    assert np.linalg.norm(J @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert np.linalg.norm(x - reference) <= 1e-8 * np.linalg.norm(reference)
    far = np.eye(k) + rng.standard_normal((k, k)) / np.sqrt(k)
    assert _gmres(far, b, _preconditioner(far, lu, np.arange(k // 3), np.arange(k // 3)), 1e-10, 5) is None
    # Contacts 5 and 9 no longer closing, 250 and 251 closing since: the old LU on the contacts in
    # both, J's own 3×3 blocks on the new ones.
    before, act = np.arange(k // 3), np.r_[np.setdiff1d(np.arange(k // 3), [5, 9]), 250, 251]
    grown = np.eye(3 * (k // 3 + 20)) + rng.standard_normal((3 * (k // 3 + 20),) * 2) / (3 * np.sqrt(k))
    grown[:k, :k] = J
    dofs = (3 * act[:, None] + np.arange(3)).ravel()
    Jn = grown[np.ix_(dofs, dofs)]
    x = _gmres(Jn, b, _preconditioner(Jn, lu, before, act), 1e-10, 40)
    assert np.linalg.norm(x - np.linalg.solve(Jn, b)) <= 1e-8 * np.linalg.norm(np.linalg.solve(Jn, b))


@pytest.mark.parametrize("mode", ["fresh", "reuse", "jacobi"])
def test_newton_reusing_its_factor_solves_the_same_problem(solve, monkeypatch, mode):
    """A Newton system of more than SINGLE_ROWS rows: with the last LU reused through GMRES
    (newton.REUSE_CHANGES = 1: whenever the closing contacts are the same), with GMRES
    preconditioned by the diagonal blocks before any LU (and no LU reused), and with neither (a
    fresh LU every step), the solve ends at the tolerance (the natural-map residual recomputed
    here) and matches the known solution within it; with either GMRES, fewer LUs than Newton
    steps."""
    from tissue.contact import newton

    factors, steps, lu, newton_step = [], [], newton._lu, newton.newton_step
    monkeypatch.setattr(newton, "_lu", lambda a: factors.append(len(a)) or lu(a))
    # steps: each Newton step's system size (3 × the closing contacts, newton_step's `closing`)
    monkeypatch.setattr(newton, "newton_step",
                        lambda *a, **k: steps.append(3 * np.count_nonzero(a[6])) or newton_step(*a, **k))
    monkeypatch.setattr(newton, "REUSE_CHANGES", 1.0)
    if mode != "reuse":
        monkeypatch.setattr(newton, "REUSE_ITERATIONS", 0)
    if mode != "jacobi":
        monkeypatch.setattr(newton, "JACOBI_ITERATIONS", 0)
    rng = np.random.default_rng(8)
    W = random_delassus(300, rng)
    W /= np.mean(np.diagonal(W))
    mu = rng.uniform(0.2, 0.8, 300)
    q, r_star = solvable_problem(W, mu, rng)
    r, info = solve(W, q, mu, tol=1e-9, max_iterations=100, method="newton")
    assert info.converged and natural_map(W, q, mu, r) <= 1e-9
    assert max(steps) >= newton.SINGLE_ROWS
    np.testing.assert_allclose(r, r_star, atol=1e-6 * np.abs(r_star).max())
    if mode != "fresh":
        assert len(factors) < len(steps)
    else:
        assert len(factors) >= len(steps)


@pytest.mark.parametrize("condition, factorised", [(1e2, ["float32"]), (1e12, ["float32", "float64"])])
def test_newton_system_solve_matches_lapack(monkeypatch, condition, factorised):
    """Newton's large systems: LU in float32 refined in float64 (well conditioned), or float64's
    LU after the refinement failed (too ill-conditioned for float32): backward stable as float64's
    LU is, and the solution of numpy's float64 solve within the conditioning's bound."""
    from tissue.contact import newton
    from tissue.contact.newton import SINGLE_ROWS, _lu_solve

    rng = np.random.default_rng(12)
    k = SINGLE_ROWS + 3
    U, _ = np.linalg.qr(rng.standard_normal((k, k)))
    V, _ = np.linalg.qr(rng.standard_normal((k, k)))
    J = (U * np.geomspace(1.0, 1.0 / condition, k)) @ V.T      # non-symmetric, as (A + B W) is; ‖J‖ = 1
    b = rng.standard_normal(k)
    dtypes, lu = [], newton._lu
    monkeypatch.setattr(newton, "_lu", lambda a: dtypes.append(str(a.dtype)) or lu(a))
    x = _lu_solve(J.copy(), b)
    assert dtypes == factorised
    reference = np.linalg.solve(J, b)
    assert np.linalg.norm(J @ x - b) <= 1e-12 * (np.linalg.norm(b) + np.linalg.norm(x))
    assert np.linalg.norm(x - reference) <= 1e-13 * condition * np.linalg.norm(reference)


@pytest.mark.parametrize("horizon", [8, 64])
def test_auto_gives_up_the_sweeps_by_their_rate_over_its_horizon(solve, monkeypatch, horizon):
    """auto's sweeps stop when, at their rate over the last phase, they would not reach the
    tolerance within AUTO_HORIZON sweeps (here phases of 4): a problem Gauss-Seidel finishes in
    36 sweeps is handed to Newton after the first phase with a horizon of 8, and finished by the
    sweeps alone with one of 64; both solve it."""
    from tissue.contact import frictional_contact, newton

    steps, newton_step = [], newton.newton_step
    monkeypatch.setattr(newton, "newton_step", lambda *a, **k: steps.append(1) or newton_step(*a, **k))
    monkeypatch.setattr(frictional_contact, "AUTO_PHASE", 4)
    monkeypatch.setattr(frictional_contact, "AUTO_HORIZON", horizon)
    rng = np.random.default_rng(11)
    W = random_delassus(40, rng)
    q = np.column_stack([rng.uniform(-1, 0.5, 40), rng.standard_normal((40, 2))]).ravel()
    _, gs = solve(W, q, 0.4, tol=1e-12, max_iterations=200, method="gauss_seidel")
    ra, auto = solve(W, q, 0.4, tol=1e-12, max_iterations=200, method="auto")
    assert gs.converged and gs.iterations == 36 and auto.converged and natural_map(W, q, 0.4, ra) <= 1e-12
    if horizon == 8:
        assert steps and auto.iterations == 4 + len(steps)
    else:
        assert not steps and auto.iterations <= frictional_contact.AUTO_SWEEPS
