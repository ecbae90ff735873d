"""Projected block Gauss-Seidel on the frictional contact problem (Jean & Moreau; Duriez et al.
2006), with Anderson acceleration: the kernel, all sweeps in one launch.

Contacts are swept in order, each contact's 3×3 problem solved exactly with the others' reactions
fixed (tissue.contact.cone.local_solve). The sweep is sequential by nature, so the whole
iteration loop runs serially inside ONE Taichi kernel (a launch costs more than a sweep of a few
hundred contacts). A sweep reads W once (contact i gathers rows 3i..3i+2 of W times r); the exact
residual needs u = W r + q, a second pass, so it is computed only when the errors met during the
sweep say "converged" (plus at the start, which lets a warm start that already solves the
problem cost 0 sweeps). Between two residual checks a sweep passes over the contacts that carry
nothing and were apart (u_n > 0) when last solved, but for every REVISIT_EVERY-th sweep: the check
sees them all again, so the stopping rule is unchanged, and most contacts within an alarm distance
never touch (the pressed liver: ~140 of ~155). With W kept as its factors, those sweeps read W
formed among the contacts in play (layouts._join_play, up to IN_PLAY_MAX of them) instead of
keeping y = Q Pᵀ r through every dof their nodes move; the same sweeps, rounding aside.

Anderson acceleration (window m = the history's size, see `history_shape`): a sweep is a
fixed-point map r <- G(r); after each sweep the next start is the combination of the last m + 1
sweeps' results whose residuals G(r) - r combine to the least norm (type II, Walker & Ni 2011),
projected on the cones. A combined start whose sweep error exceeds the previous start's is
rejected (back to the plain sweep's result, history cleared), at most ANDERSON_RESTARTS times,
then plain sweeps; the stopping test is unchanged (the exact residual). On the contact stage's
strongly coupled soft-body problems it cuts the sweeps to a tolerance 2-4x (bench/contact.py).
"""

import taichi as ti

from .cone import contact_error2, local_solve, matrix_at, project_contact, vector_at
from ..launch import replayed
from .layouts import (CONTACTS, DELASSUS, FACTORED, HORIZON, MAX_SWEEPS, PROBLEM, ROOM, STALL, TOL2, WINDOW, _gather_play,
                      _play_ascending, _play_offsets, _refresh, _residual, _spread, _wr, _wr_play)

ANDERSON_RESTARTS = 10    # rejecting a combination that starts worse than the sweep before, at most this often
REVISIT_EVERY = 8         # every this many sweeps, one that visits the contacts apart too


def history_shape(window: int, rows: int) -> tuple[tuple, tuple, int]:
    """The shapes of PROBLEM's hist and gram and the length of its `carried` for Anderson's window
    and room for `rows` rows (0: plain sweeps, one element each)."""
    return ((2 * window + 3, rows), (window, 2 * window + 2), 2 * (rows // 3) + 1) if window else ((1, 1), (1, 1), 1)


# Anderson's steps read and write the history of the contacts that have carried a reaction in this
# launch alone (the pressed liver: ~15-20 of ~150): the others' entries would all be zero. P.carried
# holds a mark per contact, then the marked contacts in ascending order, then their count; a
# contact joins when a sweep first gives it a reaction, its history zeroed then.

@ti.func
def _carried_offsets(P: ti.template()):
    """Where P.carried lists the contacts and where it counts them."""
    room = (P.carried.shape[0] - 1) // 2
    return room, 2 * room


@ti.func
def _carry_from_start(P: ti.template(), n):
    """The contacts with r ≠ 0 at the launch's start, marked and listed."""
    o_list, o_count = _carried_offsets(P)
    count = 0
    for i in range(n):
        P.carried[i] = 0
        if vector_at(P.r, i).norm_sqr() != 0.0:
            P.carried[i] = 1
            P.carried[o_list + count] = i
            count += 1
    P.carried[o_count] = count


@ti.func
def _carry(P: ti.template(), m, i):
    """Contact i, given a reaction by a sweep, into the list (in order) with its history zeroed
    (what its reactions of zero made it), unless it is there."""
    if P.carried[i] == 0:
        o_list, o_count = _carried_offsets(P)
        P.carried[i] = 1
        t = P.carried[o_count]
        while t > 0 and P.carried[o_list + t - 1] > i:
            P.carried[o_list + t] = P.carried[o_list + t - 1]
            t -= 1
        P.carried[o_list + t] = i
        P.carried[o_count] += 1
        for row in range(2 * m + 3):
            for a in ti.static(range(3)):
                P.hist[row, 3 * i + a] = 0.0


@ti.func
def _save(P: ti.template(), m, on):
    if on > 0:
        o_list, o_count = _carried_offsets(P)
        for t in range(P.carried[o_count]):
            i = P.carried[o_list + t]
            for a in ti.static(range(3)):
                P.hist[2 * m + 2, 3 * i + a] = P.r[3 * i + a]


@ti.func
def _accelerate(P: ti.template(), window, est, state):
    """After a sweep whose start had the running error `est`: state = (Anderson steps since the
    last restart, restarts left, the previous start's error). A combined start worse than the
    previous one is rejected: back to the previous sweep's result (what plain Gauss-Seidel had),
    history cleared; after ANDERSON_RESTARTS rejections, plain sweeps only."""
    since, on, last = ti.cast(state[0], ti.i32), ti.cast(state[1], ti.i32), state[2]
    o_list, o_count = _carried_offsets(P)
    if since > 1 and est > last:
        for t in range(P.carried[o_count]):
            i = P.carried[o_list + t]
            for a in ti.static(range(3)):
                P.r[3 * i + a] = P.hist[2 * window, 3 * i + a]
        since, on = 0, on - 1
    else:
        last = est
        _anderson(P, since, window)
        since += 1
    return ti.Vector([since, on, last])


@ti.func
def _anderson(P: ti.template(), k, m):
    """Anderson step after sweep k (k = 0: the first since a restart). r holds g = G(x), the
    sweep's result, and hist[2m + 2] the x it started from. hist rows 0..m-1 hold ΔG, rows m..2m-1
    ΔF (ring buffers, F = G(x) - x), rows 2m, 2m + 1 the previous g and f; gram[i, j] = ΔF_i·ΔF_j.
    r <- P_K(g - ΔG γ) with γ = argmin |f - ΔF γ| (normal equations, Cholesky), over the contacts
    listed in P.carried (the others' entries are zero)."""
    o_list, o_count = _carried_offsets(P)
    count = P.carried[o_count]
    slot = (k - 1) % m
    xr, gp, fp = 2 * m + 2, 2 * m, 2 * m + 1
    for t in range(count):
        for c in ti.static(range(3)):
            l = 3 * P.carried[o_list + t] + c
            g, f = P.r[l], P.r[l] - P.hist[xr, l]
            if k > 0:
                P.hist[slot, l] = g - P.hist[gp, l]
                P.hist[m + slot, l] = f - P.hist[fp, l]
            P.hist[gp, l], P.hist[fp, l] = g, f
    p = ti.min(k, m)
    if p > 0:
        for j in range(p):                          # the new column of the Gram matrix, and ΔFᵀ f
            a, b = 0.0, 0.0
            for t in range(count):
                for c in ti.static(range(3)):
                    l = 3 * P.carried[o_list + t] + c
                    a += P.hist[m + slot, l] * P.hist[m + j, l]
                    b += P.hist[m + j, l] * P.hist[fp, l]
            P.gram[slot, j], P.gram[j, slot], P.gram[j, m] = a, a, b
        # Cholesky of the p×p Gram matrix (regularised: its columns become nearly dependent) in
        # gram[.., m + 1 ..], then γ into gram[.., 2m + 1].
        trace = 0.0
        for j in range(p):
            trace += P.gram[j, j]
        ok = trace > 0.0
        c = m + 1
        for j in range(p):
            d = P.gram[j, j] + 1e-10 * trace
            for i in range(j):
                d -= P.gram[j, c + i] ** 2
            if d <= 0.0:
                ok = False
            d = ti.sqrt(ti.max(d, 1e-300))
            P.gram[j, c + j] = d
            for i in range(j + 1, p):
                e = P.gram[i, j]
                for t in range(j):
                    e -= P.gram[i, c + t] * P.gram[j, c + t]
                P.gram[i, c + j] = e / d
        if ok:
            y = 2 * m + 1
            for i in range(p):                      # forward: L z = ΔFᵀ f
                e = P.gram[i, m]
                for t in range(i):
                    e -= P.gram[i, c + t] * P.gram[t, y]
                P.gram[i, y] = e / P.gram[i, c + i]
            for i0 in range(p):                     # backward: Lᵀ γ = z
                i = p - 1 - i0
                e = P.gram[i, y]
                for t in range(i + 1, p):
                    e -= P.gram[t, c + i] * P.gram[t, y]
                P.gram[i, y] = e / P.gram[i, c + i]
            for t in range(count):
                i = P.carried[o_list + t]
                x = vector_at(P.r, i)
                for j in range(p):
                    for a in ti.static(range(3)):
                        x[a] -= P.gram[j, y] * P.hist[j, 3 * i + a]
                x = project_contact(x, P.mu[i])
                for a in ti.static(range(3)):
                    P.r[3 * i + a] = x[a]


@ti.func
def _carried_outside_play(W: ti.template(), P: ti.template()):
    """FACTORED: some listed contact outside W among the contacts in play holds a reaction. A sweep
    over every contact can give a contact a reaction that an Anderson step then projects to zero
    (or a rejection undoes); apart (u_n > 0), it stays out when W among those in play grows, and a
    later combination or rejection can give it a reaction again. The sweeps in play read r as
    zero outside them, so the next sweep must search (_gather_play)."""
    o_list, o_count = _carried_offsets(P)
    outside = 0
    for t in range(P.carried[o_count]):
        i = P.carried[o_list + t]
        if W.active[i] < 0 and vector_at(P.r, i).norm_sqr() != 0.0:
            outside = 1
    return outside


# ----------------------------------------------------------------------------------------------
# Gauss-Seidel: all sweeps in one launch, serial. The exact residual needs u = W r + q (one more
# pass over W), so it is computed only when the sweep's running estimate says "converged" (and at
# the start and the end); between two, u holds each contact's value when it was last solved.
# ----------------------------------------------------------------------------------------------

def run(layout: int, W, P, max_iterations: int, tol_abs: float, stall: int = 0, horizon: int | None = None):
    """Sweeps from P.r (0 sweeps: u and the residual of r alone), in one launch (replayed: the
    sweep cap, the stall phase, its horizon and the tolerance are written into P.sizes and
    P.reals); with `stall`, stopped early when that many sweeps did not halve the residual or, at
    their rate, would not reach tol_abs within `horizon` sweeps (default: max_iterations).
    Returns (sweeps, error², stalled)."""
    P.sizes[MAX_SWEEPS], P.sizes[STALL], P.reals[TOL2] = max_iterations, stall, tol_abs ** 2
    P.sizes[HORIZON] = max_iterations if horizon is None else horizon
    _sweeps_replayed(layout, W, P)
    stats = P.stats.to_numpy()
    return int(stats[0]), float(stats[1]), bool(stats[2])


@ti.kernel
def _sweeps(layout: ti.template(), W: DELASSUS, P: PROBLEM):
    """Sweeps until the residual is ≤ tol2 (squared) or max_it sweeps; with stall > 0 also when
    `stall` sweeps did not halve the residual, or would not reach tol2 within `horizon` sweeps at
    the rate of the last `stall` (stats[2] = 1: stalled), read every `stall` sweeps. FACTORED: the
    sweeps that pass over the contacts apart read W among the contacts in play (see below)."""
    n, window = P.sizes[CONTACTS], P.sizes[WINDOW]
    max_it, stall, horizon, tol2 = P.sizes[MAX_SWEEPS], P.sizes[STALL], P.sizes[HORIZON], P.reals[TOL2]
    it, est, err2, since, on, last = 0, 0.0, 0.0, 0, ANDERSON_RESTARTS if window > 0 else 0, 1e300
    phase_err2, stalled = 0.0, 0
    stale, play = 0, 0          # FACTORED: y behind r; W among the contacts in play still kept
    scan = 1                    # FACTORED: contacts may have come into play since W among them was formed
    # (y is first made by the residual at sweep 0, inside the loop: refreshed out here, at the
    # kernel's top level, its loops would each be a parallel task, a dispatch to the thread pool.)
    while True:
        if it == 0 and on > 0:
            _carry_from_start(P, n)
        if ti.static(layout == FACTORED):
            if it == 0:
                _, o_count, _ = _play_offsets(W, n)
                for i in range(n):
                    W.active[i] = -1
                W.active[o_count] = 0
                play = W.dims[ROOM] > 0
        at_phase = stall > 0 and it % stall == 0
        if it == 0 or est <= tol2 or it >= max_it or at_phase:
            err2 = _residual(layout, W, P, n)
            stale, scan = 0, 1
            if err2 <= tol2 or it >= max_it:
                break
            if at_phase:
                # Stalled: these sweeps did not halve the residual, or at their rate the horizon
                # comes before the tolerance (then the sweeps to it are spent for nothing).
                if it > 0 and (err2 > 0.25 * phase_err2 or
                               err2 * ti.pow(err2 / phase_err2, (horizon - it) / stall) > tol2):
                    stalled = 1
                    break
                phase_err2 = err2
        _save(P, window, on)
        revisit = it % REVISIT_EVERY == REVISIT_EVERY - 1
        formed = 0
        if ti.static(layout == FACTORED):
            # A sweep that passes over the contacts apart visits those in play alone (r ≠ 0 or
            # u_n ≤ 0 at its start, as the test below finds them), with r zero elsewhere: their
            # (W r)_i from W formed among them (contacts join as they come into play, up to its
            # room), a few hundred multiply-adds each, not y kept through every dof of their
            # nodes (the pressed liver: ~15 of ~110 contacts in play, ~140 dofs). The same sweep,
            # rounding aside; the others, and every residual, read y.
            # Only a residual or a sweep over every contact can bring others into play: after a
            # sweep over those in play, with Anderson's steps among them, the next needs no search
            # (unless a step gives a listed contact outside them a reaction: _carried_outside_play).
            if play and not revisit:
                formed = 1
                if scan:
                    formed = _gather_play(W, P, n)
                play = formed
            scan = 1 - formed
            if not formed and stale:
                _refresh(layout, W, P.r, n)
                stale = 0
        est = 0.0
        visits = n
        if ti.static(layout == FACTORED):
            if formed:
                _, o_count, _ = _play_offsets(W, n)
                visits = W.active[o_count]
        for visit in range(visits):
            # (formed: those in play alone, in ascending order, which the test below would visit)
            i = visit
            if ti.static(layout == FACTORED):
                if formed:
                    i = W.active[_play_ascending(W, n) + visit]
            # Contact i solved with the others fixed; est gathers the error the old r_i had (a
            # cheap running estimate of the residual). A contact that carries nothing and was
            # apart (u_n > 0) when last seen is passed over until the next residual check, which
            # sees every contact, or the next REVISIT_EVERY-th sweep (neighbours' pushes can close its
            # gap meanwhile; without it, problems stopped by the sweep cap penetrated 4-7× deeper):
            # most of those within the alarm distance never touch.
            ri = vector_at(P.r, i)
            if ri.norm_sqr() == 0.0 and P.u[3 * i] > 0.0 and not revisit:
                continue
            A = matrix_at(W.Wd, i)
            wr = ti.Vector([0.0, 0.0, 0.0])
            if formed:
                wr = _wr_play(W, P.r, n, i)
            else:
                wr = _wr(layout, W, P.r, n, i)
            ui = vector_at(P.q, i) + wr
            rnew = local_solve(A, ui - A @ ri, P.mu[i])
            for k in ti.static(range(3)):
                P.r[3 * i + k] = rnew[k]
                P.u[3 * i + k] = ui[k]
            if on > 0 and rnew.norm_sqr() != 0.0:
                _carry(P, window, i)
            est += contact_error2(ri, ui, P.mu[i])
            if ti.static(layout == FACTORED):
                dr = rnew - ri
                if not formed and dr.dot(dr) > 0.0:
                    _spread(W, n, i, dr)
        if formed:
            stale = 1
        it += 1
        if on > 0:
            acc = _accelerate(P, window, est, ti.Vector([since, on, last]))
            since, on, last = ti.cast(acc[0], ti.i32), ti.cast(acc[1], ti.i32), acc[2]
            stale = 1           # (y is refreshed where it is read next)
            if ti.static(layout == FACTORED):
                if not scan:
                    scan = _carried_outside_play(W, P)
    P.stats[0] = it
    P.stats[1] = err2
    P.stats[2] = stalled


_sweeps_replayed = replayed(_sweeps)
