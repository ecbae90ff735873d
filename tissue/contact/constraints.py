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

JDS. H is sparse with 1×3 blocks (a row touches one node per body for a vertex, up to three for a
point on a triangle).
Per body, its rows that touch it are sorted by their number of blocks (descending) and the blocks
stored "jagged diagonal" by "jagged diagonal": the k-th block of every row that has more than k
blocks, in sorted-row order, then the (k+1)-th, ... So the k-th block of sorted row i is at
jd_ptr[k] + i, and the threads of consecutive rows read consecutive memory (coalesced on a GPU).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
import taichi as ti

from .. import backend
from ..errors import TissueError
from .detection import Contacts


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


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(k, 3, 3): rows n, t1, t2 (right-handed orthonormal), t1 built from the world axis least
    aligned with n so it varies smoothly with n."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    axis = np.eye(3)[np.argmin(np.abs(n), axis=1)]
    t1 = np.cross(n, axis)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return np.stack([n, t1, np.cross(n, t1)], axis=1)


@dataclass
class ConstraintRows:
    """The rows of H as entries (row, body, node, 1×3 value), and δ_free.

    Rows [0, 3 n_contacts) are the contacts (n, t1, t2 each); the rest are attachments."""

    n_rows: int
    n_contacts: int
    row: np.ndarray
    body: np.ndarray
    node: np.ndarray
    value: np.ndarray
    q: np.ndarray
    frames: np.ndarray           # (n_contacts, 3, 3) rows n, t1, t2

    def body_matrix(self, body: int, n_nodes: int) -> sp.csr_matrix:
        """Body `body`'s block of H as a sparse (n_rows × 3 n_nodes) matrix."""
        sel = self.body == body
        r = np.repeat(self.row[sel], 3)
        c = (3 * self.node[sel][:, None] + np.arange(3)).ravel()
        return sp.csr_matrix((self.value[sel].ravel(), (r, c)), shape=(self.n_rows, 3 * n_nodes))


def build_rows(contacts: Contacts, free, prev, attachments=(), time: float = 0.0,
               frictionless=None) -> ConstraintRows:
    """H and δ_free for the contacts and attachments; free/prev: per body (n, 3) positions after
    the free motion and at the start of the step.

    frictionless: (k,) bool; those contacts' tangent rows are left empty (their reactions are zero
    whatever W says there), which spares two thirds of their share of W and of the correction."""
    k = len(contacts)
    frames = tangent_frames(contacts.normal) if k else np.zeros((0, 3, 3))
    row, body, node, value = [], [], [], []
    rows3 = 3 * np.arange(k)[:, None] + np.arange(3)              # (k, 3)
    if frictionless is not None:
        rows3 = np.where(np.asarray(frictionless)[:, None] & (np.arange(3) > 0), -1, rows3)
    disp = -contacts.other_motion
    for j in range(3):                                            # the point's own blocks: u_j d
        own = np.flatnonzero(contacts.own_weights[:, j] != 0)
        row.append(rows3[own].ravel())
        body.append(np.repeat(contacts.body[own], 3))
        node.append(np.repeat(contacts.nodes[own, j], 3))
        value.append((contacts.own_weights[own, j, None, None] * frames[own]).reshape(-1, 3))
        for b in np.unique(contacts.body[own]):
            sel = own[contacts.body[own] == b]
            nodes = contacts.nodes[sel, j]
            disp[sel] += contacts.own_weights[sel, j, None] * (free[b][nodes] - prev[b][nodes])
    soft = np.flatnonzero(contacts.soft)
    for j in range(3):                                            # the triangle's blocks: -w_j d
        row.append(rows3[soft].ravel())
        body.append(np.repeat(contacts.other[soft], 3))
        node.append(np.repeat(contacts.triangle[soft, j], 3))
        value.append((-contacts.weights[soft, j, None, None] * frames[soft]).reshape(-1, 3))
        for b in np.unique(contacts.other[soft]):
            sel = soft[contacts.other[soft] == b]
            nodes = contacts.triangle[sel, j]
            disp[sel] -= contacts.weights[sel, j, None] * (free[b][nodes] - prev[b][nodes])
    q = np.einsum("kij,kj->ki", frames, disp)
    q[:, 0] = contacts.gap
    q[rows3 < 0] = 0.0
    q = [q.ravel()]
    for a, att in enumerate(attachments):
        r = 3 * k + 3 * a + np.arange(3)
        row.append(r)
        body.append(np.full(3, att.body))
        node.append(np.full(3, att.node))
        value.append(np.eye(3))
        p = free[att.body][att.node]
        if att.other_body is None:
            target = att.target(time)
        else:
            w = np.asarray(att.weights, dtype=np.float64)
            nodes = np.asarray(att.other_nodes)
            target = w @ free[att.other_body][nodes]
            for wj, nj in zip(w, nodes):
                row.append(r)
                body.append(np.full(3, att.other_body))
                node.append(np.full(3, nj))
                value.append(-wj * np.eye(3))
        q.append(p - target)
    row, body, node = (np.concatenate(a).astype(np.int32) for a in (row, body, node))
    value = np.concatenate(value).reshape(-1, 3)
    keep = row >= 0
    return ConstraintRows(n_rows=3 * k + 3 * len(attachments), n_contacts=k, row=row[keep], body=body[keep],
                          node=node[keep], value=value[keep], q=np.concatenate(q), frames=frames)


class JaggedDiagonal:
    """One body's block of H in Jagged Diagonal Storage, on the device.

    perm[i]       the H row of sorted row i (rows sorted by block count, descending; only rows that
                  touch the body are kept: n_active of them)
    count[i]      its number of blocks
    jd_ptr[k]     start of jagged diagonal k; block k of sorted row i is entry jd_ptr[k] + i
    node[e], value[e] (1×3), row[e]   per entry

    The arrays are numpy (int32, and the backend's float type), contiguous, handed to the kernels
    as they are: on the CPU without a copy, on a GPU with one transfer per launch.
    """

    def __init__(self, rows: ConstraintRows, body: int):
        sel = np.flatnonzero(rows.body == body)
        r, nodes, values = rows.row[sel], rows.node[sel], rows.value[sel]
        count = np.bincount(r, minlength=rows.n_rows)
        order = np.argsort(-count, kind="stable")
        self.n_active = int(np.count_nonzero(count))
        perm = order[:self.n_active]
        position = np.empty(rows.n_rows, dtype=np.int64)
        position[order] = np.arange(rows.n_rows)
        by_row = np.argsort(r, kind="stable")
        starts = np.r_[0, np.cumsum(count)]
        rank = np.empty(len(r), dtype=np.int64)
        rank[by_row] = np.arange(len(r)) - starts[r[by_row]]
        lengths = np.array([np.count_nonzero(count > k) for k in range(int(count.max(initial=0)))], dtype=np.int64)
        jd_ptr = np.r_[0, np.cumsum(lengths)]
        index = jd_ptr[rank] + position[r]
        real = np.float64 if backend.current().real == ti.f64 else np.float32
        self.nnz = len(r)
        self.perm, self.count = perm.astype(np.int32), count[perm].astype(np.int32)
        self.jd_ptr = jd_ptr.astype(np.int32)
        self.node = np.empty(self.nnz, np.int32)
        self.value = np.empty((self.nnz, 3), real)
        self.row = np.empty(self.nnz, np.int32)
        self.node[index], self.value[index], self.row[index] = nodes, values, r

    def to_dense(self, n_rows: int, n_nodes: int) -> np.ndarray:
        """The block as a dense (n_rows × 3 n_nodes) matrix, read back from the JDS arrays."""
        H = np.zeros((n_rows, 3 * n_nodes))
        for k in range(len(self.jd_ptr) - 1):
            for i in range(self.jd_ptr[k + 1] - self.jd_ptr[k]):
                e = self.jd_ptr[k] + i
                H[self.perm[i], 3 * self.node[e]:3 * self.node[e] + 3] += self.value[e]
        return H
