"""The Delassus operator W kept as its factors (compliance warping's form), never formed whole.

`FactoredDelassus` is what `tissue.contact.compliance` builds and what the contact solvers
(`frictional_contact`'s Gauss-Seidel, `newton`) and the haptic loop read: products, diagonal
blocks and dense blocks among a few contacts, from the factors.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp


@dataclass
class FactoredDelassus:
    """W = scale Σ_s P_s Q_s P_sᵀ: a Delassus operator kept as its factors, the form compliance
    warping gives (tissue.contact.compliance: P_s = H R of body s on the dofs its rows touch, Q_s
    its rest compliance there), so that W is never formed: a Gauss-Seidel sweep reads the Q_s,
    which are far smaller than W when contact points outnumber the nodes they move.

    Contact i's blocks are e = ptr[i] .. ptr[i+1]-1: the 3×3 block blocks[e] of P at columns
    col[e] .. col[e]+2 of the segments' dofs side by side, in segment segment[e]. Segment s (one
    body) owns columns y_offset[s] .. y_offset[s+1]-1 and its d_s × d_s Q_s (row-major, symmetric)
    at Q[q_offset[s]:]. diagonal: W's 3×3 diagonal blocks (n, 3, 3), scale included.
    """

    ptr: np.ndarray
    col: np.ndarray
    segment: np.ndarray
    blocks: np.ndarray
    Q: np.ndarray
    y_offset: np.ndarray
    q_offset: np.ndarray
    diagonal: np.ndarray
    scale: float = 1.0

    @property
    def n(self) -> int:
        return len(self.ptr) - 1

    @property
    def shape(self) -> tuple[int, int]:
        return (3 * self.n, 3 * self.n)

    def scaled(self, factor: float) -> "FactoredDelassus":
        """factor W, sharing the factors."""
        return replace(self, scale=self.scale * factor, diagonal=self.diagonal * factor)

    def packed(self) -> np.ndarray:
        """[ptr | col | segment | y_offset | q_offset], int32: the kernels' index argument."""
        return np.concatenate([self.ptr, self.col, self.segment, self.y_offset, self.q_offset]).astype(np.int32)

    def _block_rows(self) -> np.ndarray:
        """The contact of each block."""
        return np.repeat(np.arange(self.n), np.diff(self.ptr))

    def __matmul__(self, r):
        """W r from the factors: z = Pᵀ r (the blocks of contacts with r ≠ 0), y = Q z per
        segment, then P y."""
        R = np.asarray(r, dtype=np.float64).reshape(-1, 3)
        row = self._block_rows()
        dofs = self.col[:, None] + np.arange(3)
        pushed = np.flatnonzero(R[row].any(axis=1))
        z = np.bincount(dofs[pushed].ravel(), np.einsum("eab,ea->eb", self.blocks[pushed], R[row[pushed]]).ravel(),
                        minlength=self.y_offset[-1])
        y = np.zeros_like(z)
        for s, (y0, y1) in enumerate(zip(self.y_offset[:-1], self.y_offset[1:])):
            y[y0:y1] = self._segment_Q(s) @ z[y0:y1]
        u = np.einsum("eab,eb->ea", self.blocks, y[dofs])
        return self.scale * np.bincount((3 * row[:, None] + np.arange(3)).ravel(), u.ravel(), minlength=3 * self.n)

    def _segment_Q(self, s: int) -> np.ndarray:
        d = self.y_offset[s + 1] - self.y_offset[s]
        return self.Q[self.q_offset[s]:self.q_offset[s] + d * d].reshape(d, d)

    def _P(self, contacts):
        """The blocks of P of `contacts` (ids) in segment s, per segment: {s: (P sparse (3k ×
        3|nodes|), nodes: the block columns used, P's columns in order)}."""
        contacts = np.asarray(contacts, dtype=np.int64)
        counts = self.ptr[contacts + 1] - self.ptr[contacts]
        e = np.repeat(self.ptr[contacts] - np.cumsum(np.r_[0, counts[:-1]]), counts) + np.arange(counts.sum())
        row, col, seg = np.repeat(np.arange(len(contacts)), counts), self.col[e], self.segment[e]
        out = {}
        for s in np.unique(seg):
            on = seg == s
            nodes, at = np.unique(col[on], return_inverse=True)
            ii = np.broadcast_to((3 * row[on])[:, None, None] + np.arange(3)[:, None], (on.sum(), 3, 3))
            jj = np.broadcast_to((3 * at)[:, None, None] + np.arange(3), (on.sum(), 3, 3))
            out[s] = (sp.csr_matrix((self.blocks[e[on]].ravel(), (ii.ravel(), jj.ravel())),
                                    shape=(3 * len(contacts), 3 * len(nodes))), nodes)
        return out

    def block(self, rows, cols) -> np.ndarray:
        """W between contacts `rows` and `cols` (ids) as a dense (3|rows|, 3|cols|) array: per
        segment P_rows Q P_colsᵀ with P sparse (a contact's blocks touch a few nodes) and Q among
        the nodes those blocks touch: O(nnz(P) × nodes), not O(|rows| × nodes²)."""
        Pr, Pc = self._P(rows), self._P(cols)
        W = np.zeros((3 * len(rows), 3 * len(cols)))
        for s in set(Pr) & set(Pc):
            (P, a), (R, b) = Pr[s], Pc[s]
            y0 = self.y_offset[s]
            Q = self._segment_Q(s)[np.ix_((a[:, None] - y0 + np.arange(3)).ravel(), (b[:, None] - y0 + np.arange(3)).ravel())]
            W += (R @ (P @ Q).T).T
        return self.scale * W

    def restricted(self, contacts) -> np.ndarray:
        """W among `contacts` (ids) as a dense (3k, 3k) array (see block)."""
        return self.block(contacts, contacts)

    def toarray(self) -> np.ndarray:
        """W as a dense matrix (numpy, from the factors: for checks and for callers that need W)."""
        return self.block(np.arange(self.n), np.arange(self.n))
