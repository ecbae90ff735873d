"""W on the device, by layout, and the argpacks the contact solvers' kernels take.

Every kernel takes W as one DELASSUS argpack (the layout's arrays in slots a, b, c, W's 3×3
diagonal blocks Wd, the factored layout's work vectors y, z, its sizes `dims` and its `scale`)
and the problem as one PROBLEM argpack (q, mu, the reactions r and velocities u, Anderson's
history and Gram matrix, the stats a launch reports back, and the launch's `sizes` and `reals`).
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
from .cone import _block, _contact_error2, _vec
from .storage import HostArray

DENSE, CSR, FACTORED = 0, 1, 2

DELASSUS = ti.types.argpack(a=ti.types.ndarray(), b=ti.types.ndarray(), c=ti.types.ndarray(),
                            Wd=ti.types.ndarray(), y=ti.types.ndarray(), z=ti.types.ndarray(),
                            dims=ti.types.ndarray(), scale=ti.types.ndarray())
PROBLEM = ti.types.argpack(q=ti.types.ndarray(), mu=ti.types.ndarray(), r=ti.types.ndarray(), u=ti.types.ndarray(),
                           hist=ti.types.ndarray(), gram=ti.types.ndarray(), stats=ti.types.ndarray(),
                           sizes=ti.types.ndarray(), reals=ti.types.ndarray())
# W.dims (int): the factored layout's blocks and segments. P.sizes (int): contacts, Anderson's
# window, the sweep cap, the stall phase and its horizon (gauss_seidel.run). P.reals: the squared
# tolerance.
NNZ, SEGMENTS = 0, 1
CONTACTS, WINDOW, MAX_SWEEPS, STALL, HORIZON = 0, 1, 2, 3, 4
TOL2 = 0


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
        s += _block(blocks, e) @ ti.Vector([y[c], y[c + 1], y[c + 2]])
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
        z = scale * (_block(W.b, e).transpose() @ dr)
        seg = W.a[o_seg + e]
        y0 = W.a[o_y + seg]
        d = W.a[o_y + seg + 1] - y0
        row = W.a[o_q + seg] + (W.a[o_col + e] - y0) * d
        for m in range(d):
            W.y[y0 + m] += W.c[row + m] * z[0] + W.c[row + d + m] * z[1] + W.c[row + 2 * d + m] * z[2]


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
            ri = _vec(r, i)
            for e in range(W.a[i], W.a[i + 1]):
                t = _block(W.b, e).transpose() @ ri
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
        ui = _vec(P.q, i) + _wr(layout, W, P.r, n, i)
        for k in ti.static(range(3)):
            P.u[3 * i + k] = ui[k]
    error2 = 0.0
    for i in range(n):
        error2 += _contact_error2(_vec(P.r, i), _vec(P.u, i), P.mu[i])
    return error2
