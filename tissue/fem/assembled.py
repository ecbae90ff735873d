"""The co-rotated stiffness Σ R Kₑ Rᵀ assembled once per step into 3×3 blocks, for CG products.

The paper's CG recomputes every element's product in every iteration. Assembling the rotated
blocks once per step costs about two such products; each iteration then reads ~15 blocks per node
instead of redoing the element arithmetic.

Two layouts, both over the model's capacity-sized arrays (`tissue.fem.model`), kept up to date by
the model's topology edits:
  BlockRows        full rows: each vertex sums the blocks of its incident elements into its own row
                   (block-CSR), so the loop over vertices runs in parallel with no atomics and a
                   fixed order. Its pattern is rebuilt after an edit.
  SymmetricBlocks  the diagonal and the upper triangle only, for one CPU thread: each element
                   adds its 10 distinct blocks once, and a product reads each off-diagonal block
                   once for both of its rows. An edit appends the blocks of new node pairs.

Both offer `assemble(m, w, a)` and `multiply(m, a, src)` (loops, called at kernel top level, with
the model's pack `m`, the FEM's work `w` and the matrix's own pack `a`), then
`product_row(a, v, src)` = (Σ R Kₑ Rᵀ src) at node v, `diagonal_block(a, v)`, and `to_scipy()`.
"""

import numpy as np
import scipy.sparse as sp
import taichi as ti

from .. import backend
from ..launch import replayed
from .model import BodyModel, Edit, real_numpy

PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))   # an element's corner pairs a < b

# block_count[0]: blocks in use. Members a layout does not use hold one entry. A step's argpack
# (tissue.solver.step_kernels.STEP) holds these members too.
BLOCKS = ti.types.argpack(block_count=ti.types.ndarray(), gradients=ti.types.ndarray(), rotated=ti.types.ndarray(),
                          slots=ti.types.ndarray(), index=ti.types.ndarray(), offsets=ti.types.ndarray(),
                          blocks=ti.types.ndarray(), diagonal=ti.types.ndarray(), product=ti.types.ndarray())


def real_bytes() -> int:
    return 8 if backend.current().precision == "f64" else 4


def shape_gradients(Dm_inv: np.ndarray) -> np.ndarray:
    """Rest-shape gradients ∇N of the 4 corners of each element, as columns (m, 3, 4)."""
    return np.concatenate([-Dm_inv.sum(axis=1)[:, :, None], Dm_inv.transpose(0, 2, 1)], axis=2)


@ti.func
def column(G, a):
    return ti.Vector([G[0, a], G[1, a], G[2, a]])


@ti.func
def pair_block(lam, mu, ga, gb, ha, hb):
    """The block (a, b) of one element: λ ĥₐ ĥᵦᵀ + μ ĥᵦ ĥₐᵀ + μ (gₐ·gᵦ) I (λ, μ times V)."""
    return (lam * ha).outer_product(hb) + (mu * hb).outer_product(ha) + mu * ga.dot(gb) * ti.Matrix.identity(float, 3)


@ti.func
def limit_block(m: ti.template(), w: ti.template(), e, ga, gb, rotation: ti.template()):
    """The block (a, b) of an element's active compression limit ("invertible"):
    V Σᵢ ψ''(σ̂ᵢ) (gₐ·dᵢ)(gᵦ·dᵢ) (R dᵢ)(R dᵢ)ᵀ over its active directions dᵢ (zero elsewhere)."""
    K = ti.Matrix.zero(float, 3, 3)
    if ti.static(rotation == "invertible"):
        D = w.limited[e]
        if D.norm_sqr() > 0.0:
            k = w.limit_curvature[e]
            for i in ti.static(range(3)):
                d = ti.Vector([D[0, i], D[1, i], D[2, i]])
                K += (k[i] * ga.dot(d) * gb.dot(d)) * d.outer_product(d)
            K = m.elastic[e][0] * (w.R[e] @ K @ w.R[e].transpose())
    return K


class _Blocks:
    """What both layouts share: the model, its gradients, the pack and the re-allocation."""

    def __init__(self, model: BodyModel):
        self.model = model
        self._version = None
        self.resize()
        model.subscribe(self)

    def resize(self) -> bool:
        if self._version == self.model.version:
            return False
        self._allocate()
        self._version = self.model.version
        return True

    def _types(self):
        real = backend.current().real
        return ti.types.vector(3, real), ti.types.matrix(3, 3, real), ti.types.matrix(3, 4, real)

    def _upload_gradients(self) -> None:
        """The rest-shape gradients of every element, kept on the host too (edits change rows)."""
        self._gradients = np.zeros((self.model.element_capacity, 3, 4), dtype=real_numpy())
        self._gradients[:self.model.n_elements] = shape_gradients(self.model.Dm_inv)
        self.arrays["gradients"].from_numpy(self._gradients)

    def _pack(self, **arrays) -> None:
        one = dict(rotated=(ti.i32, 1), slots=(ti.i32, 1), index=(ti.i32, 1), offsets=(ti.i32, 1),
                   diagonal=(ti.i32, 1), product=(ti.i32, 1))
        for name, (dtype, shape) in one.items():
            arrays.setdefault(name, ti.ndarray(dtype, shape))
        self.arrays = arrays
        self.pack = BLOCKS(**arrays)


class BlockRows(_Blocks):
    """Full block rows of Σ R Kₑ Rᵀ, re-assembled from the FEM's rotations (parallel-safe)."""

    def _allocate(self) -> None:
        vec3, mat3, mat34 = self._types()
        model = self.model
        self._pack(block_count=ti.ndarray(ti.i32, 1), gradients=ti.ndarray(mat34, model.element_capacity),
                   rotated=ti.ndarray(mat34, model.element_capacity),
                   offsets=ti.ndarray(ti.i32, model.node_capacity + 1),
                   diagonal=ti.ndarray(ti.i32, model.node_capacity),
                   slots=ti.ndarray(ti.types.vector(4, ti.i32), model.incidence_capacity),
                   blocks=ti.ndarray(mat3, 1), index=ti.ndarray(ti.i32, 1))
        self._build()

    def topology_changed(self, edit: Edit) -> None:
        self.resize()
        self._build()

    def _build(self) -> None:
        """The block-CSR pattern of the node graph, and for each gather entry (node v, slot k of
        its incidence row, corner 4 e + a) the block slots of (v, tₑ[b]), b = 0..3."""
        model = self.model
        n, tets = model.n_nodes, model.tets.astype(np.int64)
        rows = np.repeat(tets, 4, axis=1).reshape(-1)
        cols = np.tile(tets, (1, 4)).reshape(-1)
        keys = np.unique(rows * n + cols)
        offsets = np.zeros(model.node_capacity + 1, dtype=np.int32)
        np.cumsum(np.bincount(keys // n, minlength=n), out=offsets[1:n + 1])
        offsets[n + 1:] = offsets[n]
        self.n_blocks = len(keys)
        if self.arrays["blocks"].shape[0] < self.n_blocks:     # grows with the pattern, by doubling
            size = max(self.n_blocks, 2 * self.arrays["blocks"].shape[0])
            self.arrays["blocks"] = ti.ndarray(self._types()[1], size)
            self.arrays["index"] = ti.ndarray(ti.i32, size)
            self.pack = BLOCKS(**self.arrays)
        columns = np.zeros(self.arrays["index"].shape[0], dtype=np.int32)
        columns[:len(keys)] = keys % n
        code = model.incidence_rows                     # (capacity, slots) corner codes, −1 unused
        used = code[:n] >= 0
        node = np.broadcast_to(np.arange(n)[:, None], used.shape)[used]
        element = code[:n][used] // 4
        slots = np.zeros((model.incidence_capacity, 4), dtype=np.int32)
        flat = np.flatnonzero(used.reshape(-1))
        slots[flat] = np.searchsorted(keys, node[:, None] * n + tets[element])
        diagonal = np.zeros(model.node_capacity, dtype=np.int32)
        diagonal[:n] = np.searchsorted(keys, np.arange(n, dtype=np.int64) * (n + 1))
        self.arrays["block_count"].from_numpy(np.array([self.n_blocks], dtype=np.int32))
        self.arrays["offsets"].from_numpy(offsets)
        self.arrays["index"].from_numpy(columns)
        self.arrays["slots"].from_numpy(slots)
        self.arrays["diagonal"].from_numpy(diagonal)
        self._upload_gradients()

    @property
    def nbytes(self) -> int:
        """Bytes a product reads from the matrix: blocks, column ids, row offsets."""
        return self.n_blocks * (9 * real_bytes() + 4) + 4 * (self.model.n_nodes + 1)

    def block_values(self) -> np.ndarray:
        """The matrix's numbers, flat float64: every block, row-major, in storage order."""
        return self.arrays["blocks"].to_numpy()[:self.n_blocks].astype(np.float64).ravel()

    def to_scipy(self, values: np.ndarray | None = None) -> sp.csr_matrix:
        """The matrix in scipy; with `values`, the same pattern holding those numbers instead of
        `block_values()` (e.g. each entry's index, to gather it later without rebuilding)."""
        n = self.model.n_nodes
        values = self.block_values() if values is None else values
        offsets = self.arrays["offsets"].to_numpy()[:n + 1]
        return sp.bsr_matrix((values.reshape(-1, 3, 3), self.arrays["index"].to_numpy()[:self.n_blocks], offsets),
                             shape=(3 * n, 3 * n)).tocsr()


@ti.func
def rows_assemble(m: ti.template(), w: ti.template(), a: ti.template(), rotation: ti.template()):
    for e in range(m.counts[1]):
        a.rotated[e] = w.R[e] @ a.gradients[e]
    for v in range(m.counts[0]):
        for j in range(a.offsets[v], a.offsets[v + 1]):
            a.blocks[j] = ti.Matrix.zero(float, 3, 3)
        for k in range(m.valence[v]):
            c = m.incidence[v, k]
            e, corner = c // 4, c % 4
            grads, rotated = a.gradients[e], a.rotated[e]
            lam, mu = m.elastic[e][0] * m.elastic[e][1], m.elastic[e][0] * m.elastic[e][2]
            ga, ha = column(grads, corner), column(rotated, corner)
            slots = a.slots[v * m.incidence.shape[1] + k]
            for b in ti.static(range(4)):
                j = slots[b]  # a slot of row v: owned by this thread, so no atomic add
                a.blocks[j] = a.blocks[j] + pair_block(lam, mu, ga, column(grads, b), ha, column(rotated, b)) \
                    + limit_block(m, w, e, ga, column(grads, b), rotation)


@ti.func
def rows_product(a: ti.template(), v, src: ti.template()):
    s = ti.Vector([0.0, 0.0, 0.0])
    for j in range(a.offsets[v], a.offsets[v + 1]):
        s += a.blocks[j] @ src[a.index[j]]
    return s


class SymmetricBlocks(_Blocks):
    """Diagonal and upper-triangle blocks of Σ R Kₑ Rᵀ, assembled element by element: for a
    single thread only (elements sharing a block would race in parallel)."""

    def _allocate(self) -> None:
        vec3, mat3, mat34 = self._types()
        model = self.model
        self._pack(block_count=ti.ndarray(ti.i32, 1), gradients=ti.ndarray(mat34, model.element_capacity),
                   slots=ti.ndarray(ti.types.vector(6, ti.i32), model.element_capacity),
                   diagonal=ti.ndarray(mat3, model.node_capacity), product=ti.ndarray(vec3, model.node_capacity),
                   index=ti.ndarray(ti.types.vector(2, ti.i32), 1), blocks=ti.ndarray(mat3, 1))
        self._staging = None        # an edit's rows on the host, reused (see topology_changed)
        self._build()

    def _build(self) -> None:
        """Per element pair: its block's slot, doubled, plus 1 when corner b has the lower node
        (the element then adds the transpose of its (a, b) block)."""
        model = self.model
        n, m, tets = model.n_nodes, model.n_elements, model.tets.astype(np.int64)
        a, b = np.array(PAIRS).T
        lo, hi = np.minimum(tets[:, a], tets[:, b]), np.maximum(tets[:, a], tets[:, b])
        keys, slot = np.unique(lo * n + hi, return_inverse=True)
        self._upper = np.stack([keys // n, keys % n], axis=1).astype(np.int32)
        self._slots = np.zeros((model.element_capacity, 6), dtype=np.int32)
        self._slots[:m] = 2 * slot.reshape(m, 6) + (tets[:, b] < tets[:, a])
        self._pairs = None                          # the key -> slot map, built on the first edit
        self._upload_pattern()
        self._upload_gradients()

    def _upload_pattern(self) -> None:
        count = len(self._upper)
        if self.arrays["blocks"].shape[0] < count:   # grows with the pattern, by doubling
            size = max(count, 2 * self.arrays["blocks"].shape[0])
            self.arrays["blocks"] = ti.ndarray(self._types()[1], size)
            self.arrays["index"] = ti.ndarray(ti.types.vector(2, ti.i32), size)
            self.pack = BLOCKS(**self.arrays)
        index = np.zeros((self.arrays["index"].shape[0], 2), dtype=np.int32)
        index[:count] = self._upper
        self.arrays["index"].from_numpy(index)
        self.arrays["slots"].from_numpy(self._slots)
        self.arrays["block_count"].from_numpy(np.array([count], dtype=np.int32))

    def topology_changed(self, edit: Edit) -> None:
        if self.resize():
            return                                   # re-allocated: the pattern was rebuilt whole
        first_new = len(self._upper)
        if len(edit.moved_to):
            self._slots[edit.moved_to] = self._slots[edit.moved_from]
            self._gradients[edit.moved_to] = self._gradients[edit.moved_from]
        if len(edit.added):
            if self._pairs is None:
                self._pairs = {(int(r), int(c)): j for j, (r, c) in enumerate(self._upper)}
            new = []
            for row, t in zip(edit.added.tolist(), self.model.tets[edit.added].tolist()):   # Python ints: faster
                for k, (a, b) in enumerate(PAIRS):
                    key = (min(t[a], t[b]), max(t[a], t[b]))
                    j = self._pairs.get(key)
                    if j is None:
                        j = self._pairs[key] = len(self._upper) + len(new)
                        new.append(key)
                    self._slots[row, k] = 2 * j + (t[b] < t[a])
            if new:
                self._upper = np.concatenate([self._upper, np.array(new, dtype=np.int32)])
            self._gradients[edit.added] = shape_gradients(self.model.Dm_inv[edit.added])
        if len(self._upper) > self.arrays["blocks"].shape[0]:
            self._upload_pattern()                   # the blocks grow: everything anew
            self.arrays["gradients"].from_numpy(self._gradients)
            return
        changed = np.unique(np.concatenate([edit.added, edit.moved_to]).astype(np.int64))
        added = np.arange(first_new, len(self._upper))
        rows = max(len(changed), len(added), 1)
        if self._staging is None or len(self._staging[0]) < rows:
            rows = max(rows, 64, 2 * len(self._staging[0]) if self._staging is not None else 0)
            self._staging = (np.empty((rows, 7), np.int32), np.empty((rows, 12), real_numpy()),
                             np.empty((rows, 3), np.int32), np.zeros(1, np.int32))
        element_ints, element_reals, pairs, count = self._staging
        element_ints[len(changed):, 0] = -1
        element_ints[:len(changed), 0] = changed
        element_ints[:len(changed), 1:] = self._slots[changed]
        element_reals[:len(changed)] = self._gradients[changed].reshape(-1, 12)
        pairs[len(added):, 0] = -1
        pairs[:len(added), 0] = added
        pairs[:len(added), 1:] = self._upper[added]
        count[0] = len(self._upper)
        WRITE_SYMMETRIC_ROWS(self.pack, *self._staging)

    @property
    def n_blocks(self) -> int:
        return len(self._upper) + self.model.n_nodes

    @property
    def nbytes(self) -> int:
        """Bytes a product reads from the matrix: blocks and their row and column ids."""
        return len(self._upper) * (9 * real_bytes() + 8) + self.model.n_nodes * 9 * real_bytes()

    def block_values(self) -> np.ndarray:
        """The matrix's numbers, flat float64: the upper blocks, then the diagonal blocks, row-major."""
        n, count = self.model.n_nodes, len(self._upper)
        return np.concatenate([self.arrays["blocks"].to_numpy()[:count].ravel(),
                               self.arrays["diagonal"].to_numpy()[:n].ravel()]).astype(np.float64)

    def to_scipy(self, values: np.ndarray | None = None) -> sp.csr_matrix:
        """The matrix in scipy; with `values`, the same pattern holding those numbers instead of
        `block_values()` (e.g. each entry's index, to gather it later without rebuilding)."""
        n, count = self.model.n_nodes, len(self._upper)
        values = self.block_values() if values is None else values
        rows, cols = self._upper[:, 0], self._upper[:, 1]
        dense_index = (3 * rows[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
        dense_col = (3 * cols[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
        upper = sp.coo_matrix((values[:9 * count], (dense_index.ravel(), dense_col.ravel())), shape=(3 * n, 3 * n))
        diagonal = sp.bsr_matrix((values[9 * count:].reshape(-1, 3, 3), np.arange(n), np.arange(n + 1)),
                                 shape=(3 * n, 3 * n))
        return (upper + upper.T + diagonal).tocsr()


# One thread runs these two: read-modify-write, since `+=` on an ndarray stays an atomic (a
# compare-and-swap loop for float64 on the CPU) even in a serial loop, where a field's is demoted.


@ti.func
def symmetric_assemble(m: ti.template(), w: ti.template(), a: ti.template(), rotation: ti.template()):
    for j in range(a.block_count[0]):
        a.blocks[j] = ti.Matrix.zero(float, 3, 3)
    for v in range(m.counts[0]):
        a.diagonal[v] = ti.Matrix.zero(float, 3, 3)
    for e in range(m.counts[1]):
        t, grads = m.tets[e], a.gradients[e]
        rotated = w.R[e] @ grads
        lam, mu = m.elastic[e][0] * m.elastic[e][1], m.elastic[e][0] * m.elastic[e][2]
        for c in ti.static(range(4)):
            gc, hc = column(grads, c), column(rotated, c)
            a.diagonal[t[c]] = a.diagonal[t[c]] + pair_block(lam, mu, gc, gc, hc, hc) + limit_block(m, w, e, gc, gc, rotation)
        for k in ti.static(range(6)):
            p, q = PAIRS[k]
            gp, hp, gq, hq = column(grads, p), column(rotated, p), column(grads, q), column(rotated, q)
            code = a.slots[e][k]
            j = code // 2
            ga, ha, gb, hb = gp, hp, gq, hq
            if code % 2 != 0:   # corner q has the lower node: the block (q, p), the transpose
                ga, ha, gb, hb = gq, hq, gp, hp
            # One call site for both orders: a kernel's size is what its compilation costs.
            a.blocks[j] = a.blocks[j] + pair_block(lam, mu, ga, gb, ha, hb) + limit_block(m, w, e, ga, gb, rotation)


@ti.func
def symmetric_multiply(m: ti.template(), a: ti.template(), src: ti.template()):
    for v in range(m.counts[0]):
        a.product[v] = a.diagonal[v] @ src[v]
    # Blocks of one row mostly follow each other (sorted when built; an edit appends): their
    # row's sum and src at the row are kept in registers over the run of the row (src would be read
    # again after each store: an ndarray might alias another), the sum stored once per run.
    row, row_sum, src_row = -1, ti.Vector([0.0, 0.0, 0.0]), ti.Vector([0.0, 0.0, 0.0])
    for j in range(a.block_count[0]):
        r, c = a.index[j][0], a.index[j][1]
        if r != row:
            if row >= 0:
                a.product[row] = a.product[row] + row_sum
            row, row_sum, src_row = r, ti.Vector([0.0, 0.0, 0.0]), src[r]
        B = a.blocks[j]
        row_sum += B @ src[c]
        a.product[c] = a.product[c] + B.transpose() @ src_row
    if row >= 0:
        a.product[row] = a.product[row] + row_sum


@ti.kernel
def _write_symmetric_rows(a: BLOCKS, element_ints: ti.types.ndarray(), element_reals: ti.types.ndarray(),
                          pairs: ti.types.ndarray(), count: ti.types.ndarray()):
    """An edit's rows: per element (id, its 6 pair slots | gradients), per new block (slot, row,
    column), and the block count; a row whose id is −1 is padding."""
    ti.loop_config(serialize=True)    # a few rows: the thread pool would cost more
    for r in range(element_ints.shape[0]):
        e = element_ints[r, 0]
        if e >= 0:
            pair_slots = ti.Vector([0, 0, 0, 0, 0, 0])
            for k in ti.static(range(6)):
                pair_slots[k] = element_ints[r, 1 + k]
            a.slots[e] = pair_slots
            G = ti.Matrix.zero(float, 3, 4)
            for i, j in ti.static(ti.ndrange(3, 4)):
                G[i, j] = element_reals[r, 4 * i + j]
            a.gradients[e] = G
    ti.loop_config(serialize=True)
    for r in range(pairs.shape[0]):
        if pairs[r, 0] >= 0:
            a.index[pairs[r, 0]] = ti.Vector([pairs[r, 1], pairs[r, 2]])
    ti.loop_config(serialize=True)
    for _ in range(1):
        a.block_count[0] = count[0]


WRITE_SYMMETRIC_ROWS = replayed(_write_symmetric_rows)
