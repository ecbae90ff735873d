"""The constraint Jacobian H of one step, and its storage in Jagged Diagonal Storage (paper §3.5).

Rows. Each contact gives three rows, in the order (normal n, tangent t1, tangent t2) of the
frictional contact solver. A row of direction d on a contact point p = Σ uⱼ xⱼ of body A (a vertex:
u = (1, 0, 0)) is uⱼ dᵀ at its carrier nodes; against a soft body B at the point Σ wⱼ yⱼ of one of
its triangles, also -wⱼ dᵀ at that triangle's nodes (so H x is the relative position along d).
Each attachment (bilateral) gives three rows, the world axes: a node held at a point (possibly
moving), or held to a point Σ wⱼ yⱼ of another body.

δ_free (the value of each row at the free motion, in metres):
  normal       the gap g found by detection at the free positions,
  tangents     dᵀ (relative displacement of the two material points over the step), i.e.
               dᵀ[Σ uⱼ (x_free - x_prev)ⱼ - Σ wⱼ (y_free - y_prev)ⱼ] or minus the obstacle's motion,
  attachments  the position error x_free,p - target.
With the reactions λ (impulses) the constrained values are δ = δ_free + W λ (see compliance.py).

JDS. H is 3×3-block sparse (paper §3.5): the three rows of a contact touch the same nodes (one per
body for a vertex, up to three for a point on a triangle), so block row t (rows 3t..3t+2) has a
3×3 block at each of them. Per body, its block rows that touch it are sorted by their number of
blocks (descending) and the blocks stored "jagged diagonal" by "jagged diagonal": the k-th block
of every block row that has more than k blocks, in sorted order, then the (k+1)-th, ... So the
k-th block of sorted block row i is at jd_ptr[k] + i, and the threads of consecutive block rows
read consecutive memory (coalesced on a GPU).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
import taichi as ti

from .. import backend
from ..errors import TissueError
from .contacts import Contacts


@dataclass(frozen=True)
class Attachment:
    """Hold node `node` of soft body `body` at a point (bilateral, 3 rows).

    Either `point` (a fixed point (3,), or a function time -> point for a moving one, such as a
    grasper's jaw), or a point of another soft body: Σ weights[j] x[other_nodes[j]] of body
    `other_body`.
    """

    body: int
    node: int
    point: tuple | Callable | None = None
    other_body: int | None = None
    other_nodes: tuple = ()
    weights: tuple = ()

    def __post_init__(self):
        if (self.point is None) == (self.other_body is None):
            raise TissueError("Attachment: give either a point or another body's nodes (other_body)")
        if self.other_body is not None:
            if len(self.other_nodes) == 0 or len(self.other_nodes) != len(self.weights):
                raise TissueError("Attachment: other_nodes and weights must be non-empty and of equal length")

    def target(self, time: float) -> np.ndarray:
        p = self.point(time) if callable(self.point) else self.point
        return np.asarray(p, dtype=np.float64).reshape(3)


def offsets(counts) -> np.ndarray:
    """[0, c₀, c₀ + c₁, ...] (int64): where each of consecutive runs of `counts` starts, and the
    end. (np.r_[0, np.cumsum(counts)] costs tens of µs; this one or two.)"""
    out = np.zeros(len(counts) + 1, np.int64)
    np.add.accumulate(counts, dtype=np.int64, out=out[1:])      # (np.cumsum's, without its wrapper)
    return out


# AXIS_CROSS[a] @ n = n × e_a (e_a the world axis a)
AXIS_CROSS = np.array([[[0, 0, 0], [0, 0, 1], [0, -1, 0]], [[0, 0, -1], [0, 0, 0], [1, 0, 0]],
                       [[0, 1, 0], [-1, 0, 0], [0, 0, 0]]], dtype=np.float64)


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(k, 3, 3): rows n, t1, t2 (right-handed orthonormal), t1 = n × the world axis least aligned
    with n, so it varies smoothly with n. (Written out: np.cross costs more than the rest.)"""
    n = normals / np.sqrt(np.einsum("ki,ki->k", normals, normals))[:, None]
    t1 = np.einsum("kij,kj->ki", AXIS_CROSS[np.argmin(np.abs(n), axis=1)], n)
    t1 /= np.sqrt(np.einsum("ki,ki->k", t1, t1))[:, None]
    frames = np.empty((len(n), 3, 3))
    frames[:, 0], frames[:, 1] = n, t1
    j, k = [1, 2, 0], [2, 0, 1]                         # t2 = n × t1: t2_i = n_j t1_k - n_k t1_j
    frames[:, 2] = n[:, j] * t1[:, k] - n[:, k] * t1[:, j]
    return frames


@dataclass
class ConstraintRows:
    """The rows of H as 3×3 blocks, and δ_free.

    Block row t is rows 3t, 3t+1, 3t+2: contact t's (n, t1, t2) for t < n_contacts, then each
    attachment's three axes. Entry e is the block of block row `block[e]` at node `node[e]` of
    soft body `body[e]` (`value[e]`, 3×3: the three rows' 1×3 entries there; a frictionless
    contact's tangent rows are zero). A block row may hold two blocks at one node (they add).
    `jacobian` builds all but q (empty there), `with_free_values` adds q."""

    n_rows: int
    n_contacts: int
    block: np.ndarray
    body: np.ndarray
    node: np.ndarray
    value: np.ndarray
    q: np.ndarray
    frames: np.ndarray           # (n_contacts, 3, 3) rows n, t1, t2
    directions: np.ndarray       # (n_contacts, 3, 3) the rows' directions: frames, tangents zero where frictionless

    def body_matrix(self, body: int, n_nodes: int) -> sp.csr_matrix:
        """Body `body`'s block of H as a sparse (n_rows × 3 n_nodes) matrix."""
        sel = (self.body == body).nonzero()[0]
        r = np.broadcast_to((3 * self.block[sel])[:, None, None] + np.arange(3)[:, None], (len(sel), 3, 3))
        c = np.broadcast_to((3 * self.node[sel])[:, None, None] + np.arange(3), (len(sel), 3, 3))
        return sp.csr_matrix((self.value[sel].ravel(), (r.ravel(), c.ravel())), shape=(self.n_rows, 3 * n_nodes))


def build_rows(contacts: Contacts, free, prev, attachments=(), time: float = 0.0,
               frictionless=None) -> ConstraintRows:
    """H and δ_free for the contacts and attachments; free/prev: per body (n, 3) positions after
    the free motion and at the start of the step.

    frictionless: (k,) bool; those contacts' tangent rows are zero (their reactions are zero
    whatever W says there)."""
    return with_free_values(jacobian(contacts, attachments, frictionless), contacts, free, prev, attachments, time)


def jacobian(contacts: Contacts, attachments=(), frictionless=None) -> ConstraintRows:
    """H for the contacts and attachments (q left empty: `with_free_values`). It depends on the
    contacts' carriers, weights, triangles and normals alone, not on positions or gaps, so the
    contact stage keeps it while those stay the same (a body at rest)."""
    k = len(contacts)
    frames = tangent_frames(contacts.normal) if k else np.zeros((0, 3, 3))
    directions = frames
    if frictionless is not None and np.asarray(frictionless).any():
        directions = frames * np.where(np.asarray(frictionless)[:, None, None] & (np.arange(3) > 0)[:, None], 0.0, 1.0)
    # The point's own blocks u_j d (weights 0 left out), then the other triangle's -w_j d.
    kk, jj = (contacts.own_weights != 0).nonzero()
    soft = contacts.soft.nonzero()[0]
    block, body, node = [kk], [contacts.body[kk]], [contacts.nodes[kk, jj]]
    value = [contacts.own_weights[kk, jj, None, None] * directions[kk]]
    if len(soft):
        block.append(soft.repeat(3))
        body.append(contacts.other[soft].repeat(3))
        node.append(contacts.triangle[soft].ravel())
        value.append((-contacts.weights[soft][:, :, None, None] * directions[soft, None]).reshape(-1, 3, 3))
    eye = np.eye(3)[None] if attachments else None
    for a, att in enumerate(attachments):
        t = k + a
        block.append(np.array([t]))
        body.append(np.array([att.body]))
        node.append(np.array([att.node]))
        value.append(eye)
        if att.other_body is not None:
            w = np.asarray(att.weights, dtype=np.float64)
            nodes = np.asarray(att.other_nodes)
            block.append(np.full(len(nodes), t))
            body.append(np.full(len(nodes), att.other_body))
            node.append(nodes)
            value.append(-w[:, None, None] * eye)
    block, body, node = (_joined(a).astype(np.int32, copy=False) for a in (block, body, node))
    return ConstraintRows(n_rows=3 * k + 3 * len(attachments), n_contacts=k, block=block, body=body, node=node,
                          value=_joined(value).reshape(-1, 3, 3), q=np.zeros(0), frames=frames, directions=directions)


def with_free_values(rows: ConstraintRows, contacts: Contacts, free, prev, attachments=(),
                     time: float = 0.0) -> ConstraintRows:
    """`rows` (the Jacobian of these contacts and attachments, from `jacobian`) with δ_free: the
    gap, and the relative displacement of the two material points along t1, t2; each
    attachment's position error. free/prev: per body (n, 3) positions after the free motion and
    at the start of the step."""
    k = rows.n_contacts
    moved = _displacements(free, prev)
    soft = contacts.soft.nonzero()[0]
    disp = -contacts.other_motion
    if k:
        disp += np.einsum("kj,kjc->kc", contacts.own_weights, moved(contacts.body, contacts.nodes))
    if len(soft):
        disp[soft] -= np.einsum("kj,kjc->kc", contacts.weights[soft], moved(contacts.other[soft], contacts.triangle[soft]))
    q = np.einsum("kij,kj->ki", rows.directions, disp)
    q[:, 0] = contacts.gap
    q = [q.ravel()]
    for att in attachments:
        p = free[att.body][att.node]
        if att.other_body is None:
            target = att.target(time)
        else:
            target = np.asarray(att.weights, dtype=np.float64) @ free[att.other_body][np.asarray(att.other_nodes)]
        q.append(p - target)
    return ConstraintRows(rows.n_rows, k, rows.block, rows.body, rows.node, rows.value, _joined(q), rows.frames,
                          rows.directions)


def _joined(parts: list) -> np.ndarray:
    """np.concatenate(parts), without its copy of a single part (a scene without attachments or
    soft–soft contacts builds one part of each)."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _displacements(free, prev):
    """moved(body, nodes): the step's displacement free - prev of the nodes `nodes` (any shape) of
    the bodies `body` (broadcast along nodes' first axis). One body: subtracted at those nodes
    alone. Several: the whole bodies' displacements subtracted once and gathered once per call (a
    few hundred nodes: fewer numpy calls than gathering free and prev apart); the same numbers."""
    if len(free) == 1:
        f, p = np.asarray(free[0], dtype=np.float64), np.asarray(prev[0], dtype=np.float64)
        return lambda body, nodes: f[nodes] - p[nodes]
    offset = offsets([len(f) for f in free])
    moved = np.concatenate([np.asarray(f, dtype=np.float64) - np.asarray(p, dtype=np.float64)
                            for f, p in zip(free, prev)] or [np.zeros((0, 3))])
    return lambda body, nodes: moved[offset[body].reshape((-1,) + (1,) * (nodes.ndim - 1)) + nodes]


class JaggedDiagonal:
    """One body's block of H in Jagged Diagonal Storage of 3×3 blocks (paper §3.5), as numpy arrays.

    Block rows that touch the body (see ConstraintRows) are sorted by their number of blocks
    (descending) and their blocks stored jagged diagonal by jagged diagonal, so the threads of
    consecutive block rows read consecutive memory (coalesced on a GPU):

    perm[i]       the block row of sorted block row i (n_active of them)
    count[i]      its number of blocks
    jd_ptr[k]     start of jagged diagonal k; block k of sorted block row i is entry jd_ptr[k] + i
    node[e], value[e] (3×3), row[e]   per entry (row: its block row)
    touched       the nodes the body's rows touch (sorted); local[e]: node[e]'s index among them
    packed        [perm | count | jd_ptr | node | local | touched], int32: one kernel argument

    Contiguous numpy arrays (int32, and the backend's float type): handed to the kernels as they
    are, on the CPU without a copy, on a GPU with one transfer per launch.
    """

    def __init__(self, rows: ConstraintRows, body: int):
        sel = (rows.body == body).nonzero()[0]      # (np.flatnonzero's wrappers cost more than it)
        t = rows.block[sel]
        real = np.float64 if backend.current().real == ti.f64 else np.float32
        self.nnz = len(t)
        if len(t) and (t[1:] > t[:-1]).all():
            # At most one block per block row, in order (a body's vertices against obstacles): the
            # JDS is one jagged diagonal, the blocks as they are (what the general case gives).
            self.n_active = len(t)
            self.perm, self.count = t.astype(np.int32), np.ones(len(t), np.int32)
            self.jd_ptr = np.array([0, len(t)], np.int32)
            self.node, self.row = rows.node[sel].astype(np.int32, copy=False), self.perm.copy()
            self.value = rows.value[sel].astype(real, copy=False)
        else:
            self._sort(rows, t, sel, real)
        # The nodes the body's rows touch (sorted) and each entry's index among them: W needs the
        # compliance only between these (3 × touched columns of A₀⁻¹, not all 3n). (A mask over
        # the node ids, not np.unique's sort: a few hundred entries on a few hundred nodes.)
        present = np.zeros(int(self.node.max(initial=-1)) + 1, bool)
        present[self.node] = True
        self.touched = present.nonzero()[0].astype(np.int32)
        index = np.empty(len(present), np.int32)
        index[self.touched] = np.arange(len(self.touched), dtype=np.int32)
        self.local = index[self.node]
        self.packed = np.concatenate([self.perm, self.count, self.jd_ptr, self.node, self.local, self.touched])

    @classmethod
    def from_packed(cls, packed: np.ndarray, value: np.ndarray, row: np.ndarray, n_active: int,
                    n_diagonals: int, n_touched: int) -> "JaggedDiagonal":
        """The JDS whose `packed` (from its start on), `value` and `row` are written already
        (tissue.contact.row_writer): its other arrays as views of `packed`."""
        jds = cls.__new__(cls)
        jds.n_active, jds.nnz = n_active, len(row)
        o_node = 2 * n_active + n_diagonals + 1
        o_local = o_node + jds.nnz
        o_touched = o_local + jds.nnz
        jds.packed, jds.value, jds.row = packed[:o_touched + n_touched], value, row
        jds.perm, jds.count, jds.jd_ptr = packed[:n_active], packed[n_active:2 * n_active], packed[2 * n_active:o_node]
        jds.node, jds.local = packed[o_node:o_local], packed[o_local:o_touched]
        jds.touched = packed[o_touched:o_touched + n_touched]
        return jds

    def _sort(self, rows: ConstraintRows, t: np.ndarray, sel: np.ndarray, real) -> None:
        """perm, count, jd_ptr and the entries (node, value, row) of the block rows `t` of the
        body's entries `sel`, sorted by their number of blocks."""
        n_block_rows = rows.n_rows // 3
        by_row = t.argsort(kind="stable")             # a block row's entries keep their order
        count = np.bincount(t, minlength=n_block_rows)
        order = (-count).argsort(kind="stable")
        self.n_active = int(np.count_nonzero(count))
        position = np.empty(n_block_rows, dtype=np.int64)
        position[order] = np.arange(n_block_rows)
        starts = offsets(count)
        rank = np.empty(len(t), dtype=np.int64)
        rank[by_row] = np.arange(len(t)) - starts[t[by_row]]
        # Jagged diagonal k holds the entries of rank k, one per block row with more than k blocks
        jd_ptr = offsets(np.bincount(rank))
        index = jd_ptr[rank] + position[t]
        self.perm, self.count = order[:self.n_active].astype(np.int32), count[order[:self.n_active]].astype(np.int32)
        self.jd_ptr = jd_ptr.astype(np.int32)
        # The entries gathered in JDS order (entry e from `at[e]`; not scattered there: the 3×3
        # values gathered once).
        at = np.empty(self.nnz, np.int64)
        at[index] = np.arange(self.nnz)
        source = sel[at]
        self.node, self.row = rows.node[source].astype(np.int32, copy=False), t[at]
        self.value = rows.value[source].astype(real, copy=False)

    def to_dense(self, n_rows: int, n_nodes: int) -> np.ndarray:
        """The block as a dense (n_rows × 3 n_nodes) matrix, read back from the JDS arrays."""
        H = np.zeros((n_rows, 3 * n_nodes))
        for k in range(len(self.jd_ptr) - 1):
            for i in range(self.jd_ptr[k + 1] - self.jd_ptr[k]):
                e = self.jd_ptr[k] + i
                t, a = self.perm[i], self.node[e]
                H[3 * t:3 * t + 3, 3 * a:3 * a + 3] += self.value[e]
        return H
