"""The co-rotated stiffness Σ R Kₑ Rᵀ assembled once per step into 3×3-block CSR rows.

Beyond the paper's matrix-free product: a CG iteration then costs one row-parallel block
product (about 15 blocks per node) instead of re-deriving every element's stress from strain
(about 5.5 elements per node, each ~140 multiply-adds plus a scatter and a gather), which is
roughly 3× less arithmetic and traffic per iteration for one assembly per step. Each element's
rotated shape gradients are computed once per step; rows are then assembled by the node that
owns them, reading its incident elements through the vertex index, so there are no write
conflicts and the order is fixed (deterministic).

    R Kₐᵦ Rᵀ = V (λ ĝₐ ĝᵦᵀ + μ ĝᵦ ĝₐᵀ + μ (gₐ·gᵦ) I),   ĝ = R g,  g = ∇N (rest shape)
"""

import numpy as np
import taichi as ti

from .corotational import CorotationalFEM, int_field


def block_pattern(tets: np.ndarray, n_points: int, incidence: np.ndarray):
    """Block-CSR pattern of the node graph, and for each incidence entry (vertex v, element
    corner 4e+a) the slots of the blocks (v, tₑ[b]), b = 0..3."""
    rows = np.repeat(tets, 4, axis=1).reshape(-1).astype(np.int64)
    cols = np.tile(tets, (1, 4)).reshape(-1).astype(np.int64)
    keys = np.unique(rows * n_points + cols)
    offsets = np.zeros(n_points + 1, dtype=np.int32)
    np.cumsum(np.bincount(keys // n_points, minlength=n_points), out=offsets[1:])
    columns = (keys % n_points).astype(np.int32)
    element, corner = incidence // 4, incidence % 4
    v = tets[element, corner].astype(np.int64)
    slots = np.searchsorted(keys, v[:, None] * n_points + tets[element].astype(np.int64))
    diagonal = np.searchsorted(keys, np.arange(n_points, dtype=np.int64) * (n_points + 1))
    return offsets, columns, slots.astype(np.int32), diagonal.astype(np.int32)


@ti.data_oriented
class AssembledStiffness:
    """Block rows of Σ R Kₑ Rᵀ for one CorotationalFEM, re-assembled from its rotations."""

    def __init__(self, fem: CorotationalFEM):
        self.fem = fem
        n = fem.n_nodes
        offsets, columns, slots, diagonal = block_pattern(
            fem.mesh.tets, n, fem.incidence.to_numpy())
        real = fem.R.dtype
        # Rest shape gradients ∇N of the 4 corners (columns), and their rotations R ∇N, per element.
        inv = fem.Dm_inv.to_numpy().astype(np.float64)
        grads = np.concatenate([-inv.sum(axis=1)[:, :, None], inv.transpose(0, 2, 1)], axis=2)
        self.gradients = ti.Matrix.field(3, 4, real, fem.n_elements)
        self.rotated = ti.Matrix.field(3, 4, real, fem.n_elements)
        self.gradients.from_numpy(grads)
        self.n_blocks = len(columns)
        self.row_offsets = int_field(n + 1)
        self.columns = int_field(self.n_blocks)
        self.slots = int_field(len(slots), 4)
        self.diagonal_slot = int_field(n)
        self.blocks = ti.Matrix.field(3, 3, real, self.n_blocks)
        self.row_offsets.from_numpy(offsets)
        self.columns.from_numpy(columns)
        self.slots.from_numpy(slots)
        self.diagonal_slot.from_numpy(diagonal)

    @ti.func
    def rotate_gradients(self):
        """R ∇N of every element, with the rotations of the latest `fem.update_rotations`."""
        for e in range(self.fem.n_elements):
            self.rotated[e] = self.fem.R[e] @ self.gradients[e]

    @ti.func
    def assemble_row(self, v):
        fem = self.fem
        for j in range(self.row_offsets[v], self.row_offsets[v + 1]):
            self.blocks[j] = ti.Matrix.zero(float, 3, 3)
        for k in range(fem.incidence_offsets[v], fem.incidence_offsets[v + 1]):
            c = fem.incidence[k]
            e, a = c // 4, c % 4
            grads, rotated = self.gradients[e], self.rotated[e]
            V = fem.volume[e]
            lam, mu = V * fem.lame[e][0], V * fem.lame[e][1]
            ga = ti.Vector([grads[0, a], grads[1, a], grads[2, a]])
            ha = ti.Vector([rotated[0, a], rotated[1, a], rotated[2, a]])
            for b in ti.static(range(4)):
                gb = ti.Vector([grads[0, b], grads[1, b], grads[2, b]])
                hb = ti.Vector([rotated[0, b], rotated[1, b], rotated[2, b]])
                j = self.slots[k][b]  # a slot of row v: owned by this thread, so no atomic add
                self.blocks[j] = self.blocks[j] + (lam * ha).outer_product(hb) + (mu * hb).outer_product(ha) \
                    + mu * ga.dot(gb) * ti.Matrix.identity(float, 3)

    @ti.func
    def product_row(self, v, p):
        """(Σ R Kₑ Rᵀ p) at node v."""
        s = ti.Vector([0.0, 0.0, 0.0])
        for j in range(self.row_offsets[v], self.row_offsets[v + 1]):
            s += self.blocks[j] @ p[self.columns[j]]
        return s

    @ti.func
    def diagonal_block(self, v):
        return self.blocks[self.diagonal_slot[v]]
