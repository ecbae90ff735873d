"""The Delassus operator W kept as its factors (compliance warping's form), never formed whole.

`FactoredDelassus` is what `tissue.contact.warping` builds and what the contact solvers
(`frictional_contact`'s Gauss-Seidel, `newton`) and the haptic loop read: products, diagonal
blocks and dense blocks among a few contacts, from the factors.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import scipy.sparse as sp


@dataclass
class FactoredDelassus:
    """W = scale Σ_s P_s Q_s P_sᵀ: a Delassus operator kept as its factors, the form compliance
    warping gives (tissue.contact.warping: P_s = H R of body s on the dofs its rows touch, Q_s
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

    def scaled(self, factor: float, diagonal: np.ndarray | None = None) -> "FactoredDelassus":
        """factor × W sharing the factors; its diagonal blocks (what the local solves read) are
        `diagonal` × factor where given, else W's own × factor."""
        diagonal = self.diagonal if diagonal is None else diagonal
        return replace(self, scale=self.scale * factor, diagonal=diagonal * factor)

    def packed(self) -> np.ndarray:
        """[ptr | col | segment | y_offset | q_offset], int32: the kernels' index argument."""
        return np.concatenate([self.ptr, self.col, self.segment, self.y_offset, self.q_offset]).astype(np.int32)

    @cached_property
    def _structure(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The contact of each block, the three dofs (columns) of each block and its three rows
        (built once)."""
        row = np.repeat(np.arange(self.n), np.diff(self.ptr))
        return row, self.col[:, None] + np.arange(3), (3 * row[:, None] + np.arange(3)).ravel()

    def __matmul__(self, r):
        """W r from the factors: z = Pᵀ r (the blocks of contacts with r ≠ 0), y = Q z per
        segment, then P y."""
        R = np.asarray(r, dtype=np.float64).reshape(-1, 3)
        row, dofs, rows = self._structure
        pushed = R[row].any(axis=1).nonzero()[0]
        z = np.bincount(dofs[pushed].ravel(), np.einsum("eab,ea->eb", self.blocks[pushed], R[row[pushed]]).ravel(),
                        minlength=self.y_offset[-1])
        y = np.zeros_like(z)
        for s, (y0, y1) in enumerate(zip(self.y_offset[:-1], self.y_offset[1:])):
            y[y0:y1] = self._segment_Q(s) @ z[y0:y1]
        u = np.einsum("eab,eb->ea", self.blocks, y[dofs])
        return self.scale * np.bincount(rows, u.ravel(), minlength=3 * self.n)

    def _segment_Q(self, s: int) -> np.ndarray:
        d = self.y_offset[s + 1] - self.y_offset[s]
        return self.Q[self.q_offset[s]:self.q_offset[s] + d * d].reshape(d, d)

    @cached_property
    def _by_segment(self) -> dict:
        """Per segment s, its part of P (3n × the segment's dofs, CSR, indices sorted, explicit
        zeros kept), built once: `_P` takes rows of it."""
        row, dofs, _ = self._structure
        out = {}
        for s in np.unique(self.segment):
            on = self.segment == s
            ii = np.broadcast_to((3 * row[on])[:, None, None] + np.arange(3)[:, None], (on.sum(), 3, 3))
            jj = np.broadcast_to((dofs[on] - self.y_offset[s])[:, None, :], (on.sum(), 3, 3))
            d = self.y_offset[s + 1] - self.y_offset[s]
            out[s] = sp.csr_matrix((self.blocks[on].ravel(), (ii.ravel(), jj.ravel())), shape=(3 * self.n, d))
        return out

    def _P(self, contacts):
        """The blocks of P of `contacts` (ids) in segment s, per segment: {s: (P sparse (3k ×
        the dofs used), the segment's dofs used, in order)}: rows of `_by_segment`, its columns
        renumbered among the dofs used. Sliced with numpy gathers on the CSR arrays (a contact's
        three rows are contiguous there): scipy's fancy row indexing cost most of a block."""
        contacts = np.asarray(contacts, dtype=np.int64)
        out = {}
        for s, P in self._by_segment.items():
            start, stop = P.indptr[3 * contacts], P.indptr[3 * contacts + 3]
            lengths = stop - start
            if not lengths.any():
                continue
            entries = np.repeat(start - np.cumsum(lengths) + lengths, lengths) + np.arange(lengths.sum())
            rows = (3 * contacts[:, None] + np.arange(3)).ravel()
            indptr = np.concatenate(([0], np.cumsum(P.indptr[rows + 1] - P.indptr[rows])))
            indices = P.indices[entries]
            used = np.zeros(P.shape[1], bool)
            used[indices] = True
            renumber = np.cumsum(used) - 1
            out[s] = (sp.csr_matrix((P.data[entries], renumber[indices], indptr), shape=(len(rows), int(renumber[-1]) + 1)),
                      np.flatnonzero(used))
        return out

    def block(self, rows, cols) -> np.ndarray:
        """W between contacts `rows` and `cols` (ids) as a dense (3|rows|, 3|cols|) array: per
        segment P_rows Q P_colsᵀ with P sparse (a contact's blocks touch a few nodes) and Q among
        the nodes those blocks touch: O(nnz(P) × nodes), not O(|rows| × nodes²)."""
        Pr = self._P(rows)
        Pc = Pr if cols is rows else self._P(cols)
        W = np.zeros((3 * len(rows), 3 * len(cols)))
        for s in set(Pr) & set(Pc):
            (P, a), (R, b) = Pr[s], Pc[s]
            W += (R @ (P @ self._segment_Q(s).take(a, axis=0).take(b, axis=1)).T).T   # (take: cheaper than np.ix_)
        return self.scale * W

    def restricted(self, contacts) -> np.ndarray:
        """W among `contacts` (ids) as a dense (3k, 3k) array (see block)."""
        return self.block(contacts, contacts)

    def toarray(self) -> np.ndarray:
        """W as a dense matrix (numpy, from the factors: for checks and for callers that need W)."""
        return self.block(np.arange(self.n), np.arange(self.n))
