"""The compliance C = A⁻¹ of a body being cut, kept exact by low-rank updates (paper §4.2).

A = (1 + h α_M) M + (h α_K + h²) K₀ is the rest step matrix (as tissue.solver.reference's
rest_matrix builds it) on the free dofs; the rows and columns of held and detached nodes are zero
in C, as in rest_compliance. The body's topology edits (BodyModel.remove_elements, add_nodes,
add_elements) are recorded as the model announces them, with each element's 12×12 block
Aₑ = (1 + h α_M) Mₑ + (h α_K + h²) Kₑ; `update()` then brings C to the new matrix in up to three
low-rank steps, each C ← C − T Uᵀ with U = C G (columns of C: a gather) and T = U X, X small and
solved on the host:

  drop     dofs that stopped being free (a node left without elements): the inverse of A
           without them is C − C[:, d] C_dd⁻¹ C[d, :] (block-wise inversion read backwards);
  correct  ΔA = Σ_added Aₑ − Σ_removed Aₑ on the dofs that stay free, written G B Gᵀ, B = V Λ Vᵀ
           on its range (an element put back with a node renamed, as a cut does, changes B's
           size but barely its rank: its entries that cancel are dropped first): Woodbury in
           the form that never inverts Λ, (A + G V Λ Vᵀ Gᵀ)⁻¹ = C − U (I + Λ Vᵀ Gᵀ U)⁻¹ Λ Uᵀ
           with U = C G V;
  extend   dofs that became free (new nodes in elements): A' = [[A, E], [Eᵀ, D]], whose inverse,
           by the Schur complement S = D − Eᵀ C E, is C' = C + V S⁻¹ Vᵀ with V = [C E; −I] (C
           zero-padded to the new dofs).

Eager (fold_rank 0) folds the factors into C after every update, n² work per unit of rank (the
paper's cost). Lazy keeps them: `rows(dofs)` returns the rows of C − T Uᵀ without forming it (W
needs only the rows of the constrained nodes), and the factors are folded into C once their rank
passes `fold_rank`. Float64 only: single precision is unstable for these inversions (paper §4.3).

The three operations (gather, factor, fold) are Taichi kernels over the ndarrays; on the CPU they
run instead as numpy's BLAS on the same ndarrays' memory (tissue.launch.host_view), `blas=False`
forcing the kernels (the tests check both): one BLAS thread folds several times faster than
the kernels, and updates faster (docs/performance.md, "Cutting"; bench.cutting).
The fold updates C's upper triangle a strip of rows at a time, in place by the BLAS's dgemm
(tissue.cutting.blas: no temporary product), and mirrors it, so C stays exactly symmetric as the
kernel keeps it. The mirror is most of an eager fold's time (at rank 12-48 it costs about what
the product does): a triangle-only C would halve the traffic, but every reader (the gather, W,
the correction) reads whole rows.
"""

import numpy as np
import scipy.linalg
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem.model import BodyModel
from ..launch import host_view
from .blas import subtract_product

RANK_ROOM = 256      # factor columns beyond fold_rank, so that an update rarely folds midway
RANK_TOLERANCE = 1e-13   # eigenvalues of a correction below this fraction of its largest: rounding


# What the kernels read: C, its factors T, U and the mask of free dofs (C − T Uᵀ on the free dofs),
# bundled once per allocation.
LOW_RANK = ti.types.argpack(C=ti.types.ndarray(), T=ti.types.ndarray(), U=ti.types.ndarray(),
                            free=ti.types.ndarray())


@ti.func
def _entry(c: ti.template(), rank, i, j):
    """Entry (i, j) of C − T Uᵀ, zero unless both dofs are free."""
    value = 0.0
    if c.free[i] != 0 and c.free[j] != 0:
        value = c.C[i, j]
        for r in range(rank):
            value -= c.T[i, r] * c.U[j, r]
    return value


@ti.kernel
def _gather(c: LOW_RANK, rank: ti.i32, cols: ti.types.ndarray(), k: ti.i32, n: ti.i32,
            out: ti.types.ndarray(), block: ti.types.ndarray(), kb: ti.i32):
    """out[a] = row cols[a] of the current C − T Uᵀ (C symmetric: also its column), zero where a
    dof is not free; block = out at the columns cols (Gᵀ C G, for the host), if kb = k."""
    for a, j in ti.ndrange(k, n):
        out[a, j] = _entry(c, rank, j, cols[a])
    for a, b in ti.ndrange(kb, kb):
        block[a, b] = out[a, cols[b]]


@ti.kernel
def _factor(c: LOW_RANK, rows: ti.types.ndarray(), L: ti.types.ndarray(), X: ti.types.ndarray(),
            units: ti.types.ndarray(), r0: ti.i32, k: ti.i32, n: ti.i32, identity: ti.i32):
    """A factor pair in columns r0 … r0 + w (w = X's size): U = (C G) L (L = I when `identity`),
    less 1 at (units[b], b) where units[b] ≥ 0; then T = U X."""
    w = X.shape[0]
    for j, b in ti.ndrange(n, w):
        value = 0.0
        if identity:
            value = rows[b, j]
        else:
            for a in range(k):
                value += rows[a, j] * L[a, b]
        if units[b] == j:
            value -= 1.0
        c.U[j, r0 + b] = value
    for j, b in ti.ndrange(n, w):
        value = 0.0
        for d in range(w):
            value += c.U[j, r0 + d] * X[d, b]
        c.T[j, r0 + b] = value


@ti.kernel
def _fold(c: LOW_RANK, rank: ti.i32, n: ti.i32):
    """C ← C − T Uᵀ, zero outside the free dofs; the upper triangle mirrored, so C stays exactly
    symmetric (T Uᵀ is, up to rounding)."""
    for i in range(n):                  # a thread per row: the triangle's j ≥ i, no index division
        for j in range(i, n):
            value = _entry(c, rank, i, j)
            c.C[i, j] = value
            c.C[j, i] = value


# ---- the same three operations with numpy's BLAS on the ndarrays' own memory (CPU) -----------------


def _host_gather(C, T, U, rank, free, cols, n, out) -> None:
    """out[:k] = rows cols of C − T Uᵀ (C symmetric, so also its columns: C[j, c] − Σ T[j] U[c]),
    zero where a dof is not free: as _gather."""
    k = len(cols)
    out[:k, :n] = C[cols, :n]
    if rank:
        subtract_product(out[:k, :n], U[cols, :rank], T[:n, :rank])
    out[:k, :n] *= free[:n]
    out[:k][~free[cols]] = 0.0


def _host_factor(rows, k, L, X, units, T, U, r0, n) -> None:
    """U[:, r0 : r0 + w] = (C G) L (C G: the k gathered rows, transposed; L = I when None), less 1
    at (units[b], b) where units[b] ≥ 0; then T = U X: as _factor."""
    w = len(X)
    Uw = rows[:k, :n].T @ L if L is not None else rows[:k, :n].T.copy()
    at = np.flatnonzero(units >= 0)
    Uw[units[at], at] -= 1.0
    U[:n, r0:r0 + w] = Uw
    T[:n, r0:r0 + w] = Uw @ X


FOLD_TILE = 512      # rows of C folded per product (the strip mirrored right after, still partly in cache)


def _host_fold(C, T, U, rank, free, n) -> None:
    """C ← C − T Uᵀ on its upper triangle, a strip of rows at a time, mirrored to the lower one (C
    stays exactly symmetric), then zero outside the free dofs: as _fold."""
    for i0 in range(0, n, FOLD_TILE):
        i1 = min(i0 + FOLD_TILE, n)
        subtract_product(C[i0:i1, i0:n], T[i0:i1, :rank], U[i0:n, :rank])     # in place, no temporary
        _mirror_upper(C[i0:i1, i0:i1])
        C[i1:n, i0:i1] = C[i0:i1, i1:n].T
    fixed = np.flatnonzero(~free[:n])
    C[fixed, :n] = 0.0
    C[:n, fixed] = 0.0


def _mirror_upper(square: np.ndarray, tile: int = 64) -> None:
    """A square block's upper triangle copied onto its lower one, in strips of `tile` rows (a
    transposed copy stays in cache)."""
    b = len(square)
    for s0 in range(0, b, tile):
        s1 = min(s0 + tile, b)
        diagonal = square[s0:s1, s0:s1]
        diagonal[...] = np.triu(diagonal) + np.triu(diagonal, 1).T
        square[s1:b, s0:s1] = square[s0:s1, s1:b].T


def _symmetric(X: np.ndarray) -> np.ndarray:
    """(X + Xᵀ) / 2. Each factor pair's X is symmetric in exact arithmetic ((Λ⁻¹ + Vᵀ C V)⁻¹, S⁻¹,
    C_dd⁻¹), so T Uᵀ = U X Uᵀ is too; its rounding asymmetry would make C's rows depend on which
    side they are read from (a gather reads C − T Uᵀ by columns, the fold and the extension's
    reuse of rows by rows): at 3,841 tetrahedra the lazy error reached 2.8e-10 without this."""
    return 0.5 * (X + X.T)


def element_blocks(model: BodyModel, ids: np.ndarray, mass_weight: float, stiffness_weight: float) -> np.ndarray:
    """(k, 12, 12) blocks mass_weight Mₑ + stiffness_weight Kₑ of these elements, from the model's
    own rest data: Kₑ[a, b] = V (λ g_a g_bᵀ + μ g_b g_aᵀ + μ (g_a · g_b) I), g the shape-function
    gradients (the rows of Dm⁻¹, and minus their sum), Mₑ lumped ρ V / 4 per node."""
    Dm_inv = model.Dm_inv[ids]
    volume, lam, mu = model.elastic[ids].T
    g = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)          # (k, 4, 3)
    K = (lam[:, None, None, None, None] * np.einsum("eai,ebj->eaibj", g, g)
         + mu[:, None, None, None, None] * np.einsum("ebi,eaj->eaibj", g, g)
         + mu[:, None, None, None, None] * np.einsum("eab,ij->eaibj", np.einsum("eai,ebi->eab", g, g), np.eye(3)))
    blocks = stiffness_weight * volume[:, None, None] * K.reshape(-1, 12, 12)
    blocks[:, np.arange(12), np.arange(12)] += mass_weight * (model.density[ids] * volume / 4.0)[:, None]
    return blocks


def assemble(tets: np.ndarray, blocks: np.ndarray, dofs: np.ndarray) -> np.ndarray:
    """Σ of the element blocks among these sorted dofs, dense; entries off them are dropped."""
    out = np.zeros((len(dofs), len(dofs)))
    if len(dofs) == 0 or len(tets) == 0:
        return out
    element_dofs = (3 * tets[:, :, None] + np.arange(3)).reshape(len(tets), 12)
    at = np.minimum(np.searchsorted(dofs, element_dofs), len(dofs) - 1)
    inside = dofs[at] == element_dofs
    e, a, b = np.nonzero(inside[:, :, None] & inside[:, None, :])
    np.add.at(out, (at[e, a], at[e, b]), blocks[e, a, b])
    return out


def cancel_moved(tets: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """The blocks (removed ones negative) with the entries that cancel exactly set to zero: an
    element removed and put back with a node renamed (a cut separating its sides) has the same
    block, so its entries among the nodes not renamed cancel; summed, they would leave rounding
    that keeps the correction's rank up."""
    blocks = blocks.copy()
    removed: dict[bytes, list[int]] = {}
    for i in np.flatnonzero(blocks[:, 0, 0] < 0):          # −Aₑ: a positive diagonal negated
        removed.setdefault((-blocks[i]).tobytes(), []).append(i)
    for j in np.flatnonzero(blocks[:, 0, 0] > 0):
        same = removed.get(blocks[j].tobytes())
        if same:
            i = same.pop()
            kept = np.repeat(tets[i] == tets[j], 3)
            both = kept[:, None] & kept[None, :]
            blocks[i][both] = 0.0
            blocks[j][both] = 0.0
    return blocks


class CuttingCompliance:
    """C = A⁻¹ of a BodyModel's rest step matrix, on the device, following its topology edits;
    see the module docstring. `fold_rank` 0 is eager; above, lazy. `blas`: the algebra in numpy's
    BLAS on the ndarrays' memory (None: on the CPU) or in the kernels (False)."""

    def __init__(self, model: BodyModel, dt: float, rayleigh_mass: float = 0.0,
                 rayleigh_stiffness: float = 0.0, fold_rank: int = 0, blas: bool | None = None):
        be = backend.current()
        if be.precision != "f64":
            raise TissueError("cutting compliance: needs float64 (single precision is unstable for "
                              "these inversions)")
        if blas and be.arch != "cpu":
            raise TissueError(f"cutting compliance: blas=True works on the CPU's memory; on {be.arch} the "
                              "kernels do the algebra (blas=None)")
        self.blas = be.arch == "cpu" if blas is None else bool(blas)
        self.model = model
        self.mass_weight = 1.0 + dt * rayleigh_mass
        self.stiffness_weight = dt * rayleigh_stiffness + dt * dt
        self.fold_rank = int(fold_rank)
        self.rank = 0                   # factor columns in use (lazy)
        self.folds = 0
        self.version = 0                # counts the updates that changed C (readers keep what they read)
        m = model.n_elements
        self._count = m                 # the model's elements at its last edit
        self._tets = np.zeros((model.element_capacity, 4), dtype=np.int64)
        self._tets[:m] = model.tets
        self._blocks = np.zeros((model.element_capacity, 12, 12))
        self._blocks[:m] = element_blocks(model, np.arange(m), self.mass_weight, self.stiffness_weight)
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []     # (tets, ± blocks) since update()
        self._free = self._free_dofs(3 * model.node_capacity)
        self._allocate(3 * model.node_capacity, self.fold_rank + RANK_ROOM)
        free = np.flatnonzero(self._free)
        A = self._matrix(np.arange(m), free)
        C = np.zeros((self.capacity, self.capacity))
        C[np.ix_(free, free)] = scipy.linalg.inv(A)
        self.C.from_numpy(0.5 * (C + C.T))
        model.subscribe(self)

    # ---- storage ------------------------------------------------------------------------------

    def _allocate(self, dofs: int, rank: int) -> None:
        self.capacity = dofs
        self.C = ti.ndarray(ti.f64, (dofs, dofs))
        self.free = ti.ndarray(ti.i32, dofs)
        self.free.from_numpy(self._free.astype(np.int32))
        self._factors(rank)
        self._rows = ti.ndarray(ti.f64, (1, dofs)) if not self.blas else np.zeros((1, dofs))
        self._block = ti.ndarray(ti.f64, (1, 1))
        self._C = host_view(self.C) if self.blas else None

    def _factors(self, rank: int) -> None:
        self.T = ti.ndarray(ti.f64, (self.capacity, rank))
        self.U = ti.ndarray(ti.f64, (self.capacity, rank))
        self._T, self._U = (host_view(self.T), host_view(self.U)) if self.blas else (None, None)
        self._pack = LOW_RANK(C=self.C, T=self.T, U=self.U, free=self.free)

    def _grow(self, dofs: int) -> None:
        """Room for the model's grown node capacity: the folded C, padded with zeros."""
        self.fold()
        old = self.C.to_numpy()
        self._free = np.concatenate([self._free, np.zeros(dofs - len(self._free), dtype=bool)])
        self._allocate(dofs, self.T.shape[1])
        C = np.zeros((dofs, dofs))
        C[:len(old), :len(old)] = old
        self.C.from_numpy(C)

    @property
    def n_dofs(self) -> int:
        return 3 * self.model.n_nodes

    def _free_dofs(self, capacity: int) -> np.ndarray:
        free = np.zeros(capacity, dtype=bool)
        free[:self.n_dofs] = np.repeat(self.model.held == 0, 3)
        return free

    def _set_free(self, free: np.ndarray) -> None:
        self._free = free
        if self.blas:        # the mask's ndarray is the kernels' (from_numpy: a parallel launch)
            host_view(self.free)[:] = free
        else:
            self.free.from_numpy(free.astype(np.int32))

    def _matrix(self, elements: np.ndarray, dofs: np.ndarray) -> np.ndarray:
        """The current A among these dofs, from these elements' blocks."""
        return assemble(self._tets[elements], self._blocks[elements], dofs)

    # ---- the model's edits --------------------------------------------------------------------

    def topology_changed(self, edit) -> None:
        """Record an edit's element blocks (added +, removed −) and keep the mirror of the
        elements in the model's order (removed slots refilled from the tail, as the model does)."""
        model = self.model
        if model.element_capacity > len(self._blocks):
            grown = np.zeros((model.element_capacity, 12, 12))
            grown[:len(self._blocks)] = self._blocks
            self._blocks = grown
            self._tets = np.concatenate([self._tets, np.zeros((len(grown) - len(self._tets), 4), np.int64)])
        if len(edit.added):
            self._tets[edit.added] = model.tets[edit.added]
            self._blocks[edit.added] = element_blocks(model, edit.added, self.mass_weight, self.stiffness_weight)
            self._pending.append((self._tets[edit.added].copy(), self._blocks[edit.added].copy()))
        else:   # a removal: the removed are the refilled slots and the tail that did not move
            removed = np.concatenate([edit.moved_to, np.setdiff1d(np.arange(model.n_elements, self._count),
                                                                  edit.moved_from)])
            self._pending.append((self._tets[removed].copy(), -self._blocks[removed]))
            self._tets[edit.moved_to] = self._tets[edit.moved_from]
            self._blocks[edit.moved_to] = self._blocks[edit.moved_from]
        self._count = model.n_elements

    # ---- the update ---------------------------------------------------------------------------

    def update(self) -> None:
        """Bring C to the model's current matrix (the edits since the last update, in one go)."""
        if 3 * self.model.node_capacity > self.capacity:
            self._grow(3 * self.model.node_capacity)
        old, new = self._free, self._free_dofs(self.capacity)
        if not self._pending and np.array_equal(old, new):
            return
        self.version += 1
        tets = np.concatenate([t for t, _ in self._pending]) if self._pending else np.zeros((0, 4), np.int64)
        blocks = np.concatenate([b for _, b in self._pending]) if self._pending else np.zeros((0, 12, 12))
        self._pending = []
        dropped = np.flatnonzero(old & ~new)
        if len(dropped):
            C_dd = self._columns(dropped)
            self._add_factor(_symmetric(np.linalg.inv(_symmetric(C_dd))))
            self._set_free(old & new)
        kept = np.intersect1d((3 * tets[:, :, None] + np.arange(3)).reshape(-1), np.flatnonzero(old & new))
        B = assemble(tets, cancel_moved(tets, blocks), kept)
        if np.any(B):
            # The rank of B, not its size, sets the cost: B = V Λ Vᵀ, eigenvalues within rounding
            # of ‖B‖ dropped, and the Woodbury step on the columns G V, with X = (I + Λ Vᵀ C_gg V)⁻¹ Λ.
            w, V = np.linalg.eigh(B)
            keep = np.abs(w) > RANK_TOLERANCE * np.abs(w).max()
            w, V = w[keep], V[:, keep]
            C_gg = self._columns(kept)
            self._add_factor(_symmetric(np.linalg.solve(np.eye(len(w)) + w[:, None] * (V.T @ C_gg @ V), np.diag(w))),
                             L=V)
            corrected = (kept, len(w))
        else:
            corrected = None
        gained = np.flatnonzero(new & ~old)
        if len(gained):
            self._extend(gained, new, corrected)
        self._set_free(new)
        if self.rank > self.fold_rank:
            self.fold()

    def _extend(self, gained: np.ndarray, free: np.ndarray, corrected=None) -> None:
        """Block-wise inversion for the dofs that became free, by the Schur complement.
        `corrected`: (the dofs gathered for the correction just applied, its rank), whose rows
        serve here when they cover the ones needed (_corrected_columns)."""
        nodes = np.unique(gained // 3)
        codes = self.model.incidence_rows[nodes].reshape(-1)
        elements = np.unique(codes[codes >= 0] // 4)
        near = np.intersect1d((3 * self._tets[elements, :, None] + np.arange(3)).reshape(-1), np.flatnonzero(free))
        A = self._matrix(elements, near)
        g, a = np.isin(near, gained, invert=True), np.isin(near, gained)
        E, D = A[np.ix_(g, a)], A[np.ix_(a, a)]
        C_gg = self._corrected_columns(near[g], *corrected) if corrected is not None and self.blas \
            and np.isin(near[g], corrected[0]).all() else self._columns(near[g])
        self._add_factor(-_symmetric(np.linalg.inv(_symmetric(D - E.T @ C_gg @ E))), L=E, units=gained)

    def _corrected_columns(self, dofs: np.ndarray, gathered: np.ndarray, w: int) -> np.ndarray:
        """As _columns(dofs) (CPU), where `dofs` are among the rows last gathered (at the sorted
        `gathered`) and the only change since is the last factor pair, of rank w: the rows of
        C − T Uᵀ are those rows less T[dofs] U_wᵀ, n k w multiply-adds instead of a gather's
        n k (rank + 1) reading C (the new nodes' neighbours are among the correction's dofs)."""
        n, r1 = self.n_dofs, self.rank
        r0 = r1 - w
        rows = self._rows[np.searchsorted(gathered, dofs), :n] - self._T[dofs, r0:r1] @ self._U[:n, r0:r1].T
        self._rows[:len(dofs), :n] = rows
        self._gathered = len(dofs)
        return rows[:, dofs].copy()

    def _columns(self, dofs: np.ndarray, block: bool = True) -> np.ndarray | None:
        """Gather the current C's columns at these dofs (into self._rows); returns Gᵀ C G if
        `block` (its own small array: rows() may gather thousands of rows)."""
        k = len(dofs)
        if self._rows.shape[0] < k:
            shape = (max(k, 2 * self._rows.shape[0]), self.capacity)
            self._rows = np.zeros(shape) if self.blas else ti.ndarray(ti.f64, shape)
        self._gathered = k
        if block and not self.blas and self._block.shape[0] < k:
            self._block = ti.ndarray(ti.f64, (max(k, 2 * self._block.shape[0]),) * 2)
        self._gather_rows(dofs, self._rows, block)
        if self.blas:
            return self._rows[:k, dofs].copy() if block else None
        return self._block.to_numpy()[:k, :k] if block else None

    def _gather_rows(self, dofs: np.ndarray, out, block: bool = False) -> None:
        """out[:k] = the rows (C symmetric: the columns) of the current C at these dofs, up to 3
        nodes: numpy's BLAS into a numpy array, else the kernel into an ndarray (and self._block =
        Gᵀ C G if `block`)."""
        k = len(dofs)
        if self.blas:
            _host_gather(self._C, self._T, self._U, self.rank, self._free, dofs, self.n_dofs, out)
            return
        cols = np.zeros(max(k, 1), dtype=np.int32)     # never empty: Taichi takes no empty array
        cols[:k] = dofs
        _gather(self._pack, self.rank, cols, k, self.n_dofs, out, self._block, k if block else 0)

    def _add_factor(self, X: np.ndarray, L: np.ndarray | None = None, units: np.ndarray | None = None) -> None:
        """Append U = (the gathered columns) L − I[:, units], T = U X to the factors."""
        k, w = self._gathered, len(X)
        if self.rank + w > self.T.shape[1]:
            self.fold()
            if w > self.T.shape[1]:
                self._factors(w + self.fold_rank + RANK_ROOM)
        units = np.full(w, -1, dtype=np.int32) if units is None else units.astype(np.int32)
        if self.blas:
            _host_factor(self._rows, k, L, X, units, self._T, self._U, self.rank, self.n_dofs)
            self.rank += w
            return
        left = np.zeros((max(k, 1), w))
        if L is not None:
            left[:k] = L
        _factor(self._pack, self._rows, left, np.ascontiguousarray(X), units, self.rank, k, self.n_dofs,
                int(L is None))
        self.rank += w

    def fold(self) -> None:
        """C ← C − T Uᵀ (zero outside the free dofs); the factors are emptied."""
        if self.rank:
            n = min(self.n_dofs, self.capacity)       # (before a growth)
            if self.blas:
                _host_fold(self._C, self._T, self._U, self.rank, self._free, n)
            else:
                _fold(self._pack, self.rank, n)
            self.rank = 0
            self.folds += 1

    # ---- what the rest reads ------------------------------------------------------------------

    def rows(self, dofs) -> np.ndarray:
        """(len(dofs), 3 nodes) these rows of the current C, without forming it."""
        self.update()
        dofs = np.asarray(dofs, dtype=np.int64).reshape(-1)
        self._columns(dofs, block=False)
        if self.blas:
            return self._rows[:len(dofs), :self.n_dofs].copy()
        return self._rows.to_numpy()[:len(dofs), :self.n_dofs]

    def rows_into(self, dofs, out) -> None:
        """These rows of the current C, without forming it, into the first len(dofs) rows of
        `out`, a float64 ndarray (≥ len(dofs), capacity) (the contact kernels read it); its columns
        past 3 nodes are left as they are."""
        self.update()
        dofs = np.asarray(dofs, dtype=np.int64).reshape(-1)
        self._gather_rows(dofs, host_view(out) if self.blas else out)

    def dense(self) -> np.ndarray:
        """The whole current C (3 nodes × 3 nodes), from its rows (lazy factors kept)."""
        return self.rows(np.arange(self.n_dofs))
