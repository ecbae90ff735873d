"""Relaxed block Jacobi on the frictional contact problem: every contact solved in parallel from
the previous iterate, then relaxed, r <- r + omega (r_local - r). Parallel (for GPUs and thousands
of contacts) but it converges markedly slower than Gauss-Seidel on coupled problems (5-10x more
iterations on the tests' problems). omega starts at min(1, 1/lambda_max(D^-1 W)) (D the 3x3
diagonal blocks; for the LCP relaxed block Jacobi converges when omega < 2/lambda_max). Safeguard:
the residual is read every JACOBI_CHECK_EVERY iterations; when it exceeds twice the best seen, or
the best has not improved for JACOBI_STALL_CHECKS checks, the best iterate is restored and omega
halved. One launch per stage, everything parallel.
"""

import numpy as np
import taichi as ti

from .. import backend
from .cone import contact_error2, local_solve, matrix_at, vector_at
from .layouts import CONTACTS, DELASSUS, PROBLEM, _refresh, _wr, array

JACOBI_CHECK_EVERY = 10   # the residual is read back (a device sync) every this many iterations
JACOBI_STALL_CHECKS = 20  # ... and omega halved after this many checks without a new best residual


def solve(layout: int, W, P, omega: float, max_iterations: int, tol_abs: float):
    """Jacobi iterations from P.r until the natural-map error is at most tol_abs or
    max_iterations; P.r ends at the best iterate seen. Returns (iterations, the last omega)."""
    best = np.inf
    r_best = array(P.r.shape, backend.current().real)
    it = stalled = 0
    while True:
        _matvec(layout, W, P)
        if it % JACOBI_CHECK_EVERY == 0 or it >= max_iterations:
            _error2_kernel(P)
            err = float(np.sqrt(P.stats.to_numpy()[1]))
            if err <= tol_abs or it >= max_iterations:
                break
            if err < best:
                best, stalled = err, 0
                r_best.copy_from(P.r)
            else:
                stalled += 1
            # Diverging or cycling: back to the best iterate and relax harder.
            if (err > 2.0 * best or stalled >= JACOBI_STALL_CHECKS) and omega > 1e-6:
                omega, stalled = 0.5 * omega, 0
                P.r.copy_from(r_best)
                _matvec(layout, W, P)
        _jacobi_step(W, P, omega)
        it += 1
    if err > best:                              # hand back the best iterate seen
        P.r.copy_from(r_best)
    return it, omega


@ti.kernel
def _matvec(layout: ti.template(), W: DELASSUS, P: PROBLEM):
    """u = W r + q (FACTORED: y refreshed on one thread first, then every contact in parallel)."""
    n = P.sizes[CONTACTS]
    for _ in range(1):
        _refresh(layout, W, P.r, n)
    for i in range(n):
        ui = vector_at(P.q, i) + _wr(layout, W, P.r, n, i)
        for k in ti.static(range(3)):
            P.u[3 * i + k] = ui[k]


@ti.kernel
def _jacobi_step(W: DELASSUS, P: PROBLEM, omega: float):
    for i in range(P.sizes[CONTACTS]):
        A = matrix_at(W.Wd, i)
        ri = vector_at(P.r, i)
        d = local_solve(A, vector_at(P.u, i) - A @ ri, P.mu[i]) - ri
        for c in ti.static(range(3)):               # a convex combination stays in the cone
            P.r[3 * i + c] += omega * d[c]


@ti.kernel
def _error2_kernel(P: PROBLEM):
    P.stats[1] = 0.0
    for i in range(P.sizes[CONTACTS]):
        P.stats[1] += contact_error2(vector_at(P.r, i), vector_at(P.u, i), P.mu[i])
