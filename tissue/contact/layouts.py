"""W on the device, by layout, and the argpacks the contact solvers' kernels take.

Every kernel takes W as one DELASSUS argpack (the layout's arrays in slots a, b, c, W's 3×3
diagonal blocks Wd, the factored layout's work vectors y, z and its scratch for W among the
contacts in play (`active`, `dense`: see gauss_seidel), its sizes `dims` and its `scale`)
and the problem as one PROBLEM argpack (q, mu, the reactions r and velocities u, Anderson's
history, Gram matrix and list of the contacts it keeps history for (`carried`), the stats a launch
reports back, and the launch's `sizes` and `reals`).
Slots by layout:
  DENSE     a = W (3n × 3n, row-major, flat)
  CSR       a = indptr, b = indices, c = blocks (3×3 block (i, indices[k]) of W in blocks[k])
  FACTORED  a = index, b = blocks, c = Q (FactoredDelassus.packed()); y = scale Q Pᵀ r, z = Pᵀ r
Dense and block-CSR gather row i of W times r (no atomics; sums in registers). The factored
layout keeps y up to date instead: (W r)_i = P_i y, and a change Δr_i adds scale Q P_iᵀ Δr_i
to y (three rows of Q per block of P_i, read in memory order). A layout's unused members hold one
element.

Every array is capacity-sized (tissue.contact.storage: kept between solves, grown by doubling), so
the kernels read the problem's sizes from `P.sizes` and `W.dims`, never from the arrays' shapes,
and the scalars that change from launch to launch (the sweep cap, the tolerance, W's scale) from
arrays too: the argpacks are built once per capacity and the launches over them replay
(tissue.launch). On the CPU the arrays are numpy (Storage's `host`: allocating a Taichi ndarray
costs more than a whole solve of a hundred contacts).
"""

import numpy as np
import taichi as ti

from .. import backend
from .cone import contact_error2, matrix_at, vector_at
from .storage import HostArray

DENSE, CSR, FACTORED = 0, 1, 2

DELASSUS = ti.types.argpack(a=ti.types.ndarray(), b=ti.types.ndarray(), c=ti.types.ndarray(),
                            Wd=ti.types.ndarray(), y=ti.types.ndarray(), z=ti.types.ndarray(),
                            active=ti.types.ndarray(), dense=ti.types.ndarray(),
                            dims=ti.types.ndarray(), scale=ti.types.ndarray())
PROBLEM = ti.types.argpack(q=ti.types.ndarray(), mu=ti.types.ndarray(), r=ti.types.ndarray(), u=ti.types.ndarray(),
                           hist=ti.types.ndarray(), gram=ti.types.ndarray(), carried=ti.types.ndarray(),
                           stats=ti.types.ndarray(), sizes=ti.types.ndarray(), reals=ti.types.ndarray())
# W.dims (int): the factored layout's blocks, segments and room for contacts in play (gauss_seidel's
# dense W among them: `active` holds each contact's slot there (n), the slots' contacts (room), their
# count and the same contacts in ascending order (room: play_length); `dense` that W, 3 room × 3 room,
# then one contact's row of P Q, 3 × the dofs). P.carried (int): the contacts that carried a reaction
# in the launch, whose Anderson history is kept (marks, list, count: gauss_seidel's block comment
# before _carried_offsets).
# P.sizes (int): contacts, Anderson's window, the sweep cap, the stall phase and its horizon
# (gauss_seidel.run). P.reals: the squared tolerance.
NNZ, SEGMENTS, ROOM = 0, 1, 2
IN_PLAY_MAX = 64      # the factored layout's sweeps form W among at most this many contacts in play
CONTACTS, WINDOW, MAX_SWEEPS, STALL, HORIZON = 0, 1, 2, 3, 4
TOL2 = 0


def play_length(n: int, room: int) -> int:
    """The length of W.active for n contacts and room for `room` in play (_play_offsets' layout)."""
    return n + 2 * room + 1


def array(shape, dtype):
    """A zeroed kernel argument: numpy on the CPU, a Taichi ndarray elsewhere."""
    if backend.current().arch == "cpu":
        npt = np.int32 if dtype == ti.i32 else (np.float64 if dtype == ti.f64 else np.float32)
        return np.zeros(shape, dtype=npt).view(HostArray)
    return ti.ndarray(dtype=dtype, shape=shape)


@ti.func
def _wr_dense(W: ti.template(), r: ti.template(), m, i):
    s0, s1, s2 = 0.0, 0.0, 0.0
    for l in range(m):
        rl = r[l]
        s0 += W[3 * i * m + l] * rl
        s1 += W[(3 * i + 1) * m + l] * rl
        s2 += W[(3 * i + 2) * m + l] * rl
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
def _factored_offsets(W: ti.template(), n):
    """Offsets of ptr, col, segment, y_offset, q_offset in FactoredDelassus.packed(), and the
    number of segments."""
    nnz, segments = W.dims[NNZ], W.dims[SEGMENTS]
    o_col = n + 1
    o_seg = o_col + nnz
    o_y = o_seg + nnz
    return o_col, o_seg, o_y, o_y + segments + 1, segments


@ti.func
def _wr_factored(index: ti.template(), blocks: ti.template(), y: ti.template(), n, i):
    o_col = n + 1
    s = ti.Vector([0.0, 0.0, 0.0])
    for e in range(index[i], index[i + 1]):
        c = index[o_col + e]
        s += matrix_at(blocks, e) @ ti.Vector([y[c], y[c + 1], y[c + 2]])
    return s


@ti.func
def _wr(layout: ti.template(), W: ti.template(), r: ti.template(), n, i):
    """(W r)_i of n contacts (for FACTORED: P_i y, with y up to date)."""
    s = ti.Vector([0.0, 0.0, 0.0])
    if ti.static(layout == DENSE):
        s = _wr_dense(W.a, r, 3 * n, i)
    elif ti.static(layout == CSR):
        s = _wr_csr(W.a, W.b, W.c, r, i)
    else:
        s = _wr_factored(W.a, W.b, W.y, n, i)
    return s


@ti.func
def _spread(W: ti.template(), n, i, dr):
    """FACTORED: y += scale Q P_iᵀ dr: for each block of contact i, three rows of its segment's Q."""
    o_col, o_seg, o_y, o_q, _ = _factored_offsets(W, n)
    scale = W.scale[0]
    for e in range(W.a[i], W.a[i + 1]):
        z = scale * (matrix_at(W.b, e).transpose() @ dr)
        seg = W.a[o_seg + e]
        y0 = W.a[o_y + seg]
        d = W.a[o_y + seg + 1] - y0
        row = W.a[o_q + seg] + (W.a[o_col + e] - y0) * d
        for m in range(d):
            W.y[y0 + m] += W.c[row + m] * z[0] + W.c[row + d + m] * z[1] + W.c[row + 2 * d + m] * z[2]


@ti.func
def _play_offsets(W: ti.template(), n):
    """FACTORED: where `active` lists the slots' contacts and their count, and the row length of
    W among the contacts in play in `dense` (3 × its room)."""
    room = W.dims[ROOM]
    return n, n + room, 3 * room


@ti.func
def _play_ascending(W: ti.template(), n):
    """FACTORED: where `active` lists the contacts in play in ascending order (after their count)."""
    return n + W.dims[ROOM] + 1


@ti.func
def _in_play(r: ti.template(), u: ti.template(), i):
    """Contact i carries a reaction or touched (u_n ≤ 0) when last solved: a sweep visits it (the
    negation of the sweeps' skip test, whatever the numbers)."""
    return not (vector_at(r, i).norm_sqr() == 0.0 and u[3 * i] > 0.0)


@ti.func
def _join_play(W: ti.template(), n, i):
    """FACTORED: contact i into the next slot s of W among the contacts in play: first V = P_i Q
    (3 × the dofs, after W in `dense`; three rows of its segment's Q per block, as _spread reads
    them), then W's blocks between i and each contact j in play (i included), scale V P_jᵀ, into
    row s and, mirrored, column s."""
    o_col, o_seg, o_y, o_q, segments = _factored_offsets(W, n)
    o_list, o_count, stride = _play_offsets(W, n)
    s = W.active[o_count]
    ov = stride * stride
    dofs = W.a[o_y + segments]
    for k in range(3 * dofs):
        W.dense[ov + k] = 0.0
    for e in range(W.a[i], W.a[i + 1]):
        B = matrix_at(W.b, e)
        seg = W.a[o_seg + e]
        y0 = W.a[o_y + seg]
        d = W.a[o_y + seg + 1] - y0
        row = W.a[o_q + seg] + (W.a[o_col + e] - y0) * d
        for m in range(d):
            v = B @ ti.Vector([W.c[row + m], W.c[row + d + m], W.c[row + 2 * d + m]])
            for a in ti.static(range(3)):
                W.dense[ov + a * dofs + y0 + m] += v[a]
    W.active[i] = s
    W.active[o_list + s] = i
    W.active[o_count] = s + 1
    o_ascending = _play_ascending(W, n)
    at = s
    while at > 0 and W.active[o_ascending + at - 1] > i:
        W.active[o_ascending + at] = W.active[o_ascending + at - 1]
        at -= 1
    W.active[o_ascending + at] = i
    scale = W.scale[0]
    for t in range(s + 1):
        j = W.active[o_list + t]
        G = ti.Matrix.zero(float, 3, 3)
        for f in range(W.a[j], W.a[j + 1]):
            c = ov + W.a[o_col + f]
            V = ti.Matrix.zero(float, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                V[a, b] = W.dense[c + a * dofs + b]
            G += V @ matrix_at(W.b, f).transpose()
        for a, b in ti.static(ti.ndrange(3, 3)):
            W.dense[(3 * s + a) * stride + 3 * t + b] = scale * G[a, b]
        if t != s:
            for a, b in ti.static(ti.ndrange(3, 3)):
                W.dense[(3 * t + b) * stride + 3 * s + a] = scale * G[a, b]


@ti.func
def _gather_play(W: ti.template(), P: ti.template(), n):
    """FACTORED: the contacts in play (_in_play) not yet among those W is formed between, joined
    (_join_play); 0, joining none, when they would exceed its room."""
    o_list, o_count, stride = _play_offsets(W, n)
    new = 0
    for i in range(n):
        if W.active[i] < 0 and _in_play(P.r, P.u, i):
            new += 1
    fits = 0
    if W.active[o_count] + new <= W.dims[ROOM]:
        fits = 1
        if new > 0:
            for i in range(n):
                if W.active[i] < 0 and _in_play(P.r, P.u, i):
                    _join_play(W, n, i)
    return fits


@ti.func
def _wr_play(W: ti.template(), r: ti.template(), n, i):
    """FACTORED: (W r)_i from W among the contacts in play, contact i among them and r zero
    outside them."""
    o_list, o_count, stride = _play_offsets(W, n)
    s = W.active[i]
    out = ti.Vector([0.0, 0.0, 0.0])
    for t in range(W.active[o_count]):
        rj = vector_at(r, W.active[o_list + t])
        for a in ti.static(range(3)):
            base = (3 * s + a) * stride + 3 * t
            out[a] += W.dense[base] * rj[0] + W.dense[base + 1] * rj[1] + W.dense[base + 2] * rj[2]
    return out


@ti.func
def _refresh(layout: ti.template(), W: ti.template(), r: ti.template(), n):
    """FACTORED: y = scale Q Pᵀ r from scratch (z = Pᵀ r first, then one product per segment);
    after a change of r other than one contact's (a start, an Anderson step), and before the
    exact residual, so rounding in the running updates never accumulates into it."""
    if ti.static(layout == FACTORED):
        o_col, o_seg, o_y, o_q, segments = _factored_offsets(W, n)
        scale = W.scale[0]
        for k in range(W.a[o_q - 1]):
            W.z[k] = 0.0
        for i in range(n):
            ri = vector_at(r, i)
            for e in range(W.a[i], W.a[i + 1]):
                t = matrix_at(W.b, e).transpose() @ ri
                col = W.a[o_col + e]
                for k in ti.static(range(3)):
                    W.z[col + k] += t[k]
        for k in range(W.a[o_q - 1]):
            W.y[k] = 0.0
        for seg in range(segments):
            # y += scale z_m Q[m, :] for each dof m with z_m ≠ 0 (Q symmetric: a row, in memory
            # order); most contacts carry no reaction, so most of z is zero.
            y0 = W.a[o_y + seg]
            d = W.a[o_y + seg + 1] - y0
            row = W.a[o_q + seg]
            for m in range(d):
                zm = scale * W.z[y0 + m]
                if zm != 0.0:
                    for k in range(d):
                        W.y[y0 + k] += W.c[row + m * d + k] * zm


@ti.func
def _residual(layout: ti.template(), W: ti.template(), P: ti.template(), n):
    """u = W r + q for each of the n contacts, and the squared natural-map error of r."""
    _refresh(layout, W, P.r, n)
    for i in range(n):
        ui = vector_at(P.q, i) + _wr(layout, W, P.r, n, i)
        for k in ti.static(range(3)):
            P.u[3 * i + k] = ui[k]
    error2 = 0.0
    for i in range(n):
        error2 += contact_error2(vector_at(P.r, i), vector_at(P.u, i), P.mu[i])
    return error2
