"""A two-level preconditioner for the implicit-Euler CG: Chebyshev smoothing with this step's
co-rotated matrix, and a coarse correction by the rest-shape coarse inverse warped by the nodal
rotations (compliance warping, paper §3.2, restricted to a coarse space).

Coarse space: a regular tetrahedral grid over the body's bounding box (about `coarse_nodes`
nodes; those no fine node lies near are dropped). P interpolates the coarse nodes barycentrically
at each fine node (≤ 4 per row; zero rows at fixed nodes). At rest the Galerkin operator
A_c = Pᵀ A₀ P is inverted once (dense). When the body turns, A ≈ R A₀ Rᵀ with R the nodal
rotations, so the rotated space R P has the Galerkin operator (R P)ᵀ A (R P) ≈ A_c, and the
coarse correction is R P A_c⁻¹ Pᵀ Rᵀ: no refactorisation per step.

V-cycle, symmetric so that PCG stays valid (the preconditioner is SPD for any SPD A_c as long as
the smoother converges):

    z = S r,   z += R P A_c⁻¹ Pᵀ Rᵀ (r - A z),   z += S (r - A z)

S is the Chebyshev polynomial of degree `degree` in D⁻¹A (D: the 3×3 diagonal blocks) that is
small on [λ/15, λ], λ = 1.1 λ_max(D₀⁻¹A₀) estimated once at rest (a rotation of the body leaves
the spectrum of D⁻¹A unchanged; removing fixed dofs only lowers λ_max). Cost per application:
2·degree products with A, a restriction and a prolongation over 4 coarse nodes per fine node,
and one dense product with A_c⁻¹ (3·coarse nodes)².
"""

import math

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import taichi as ti

from .. import backend
from ..fem.rotations import nodal_rotation
from ..fem.model import real_numpy
from ..mesh import box
from ..mesh.embedding import EmbeddedSurface
from .operator import factors, multiply, operator_row
from .state import DONE

# Chebyshev targets [λ/15, λ]: the part of the spectrum the coarse space misses. Against [λ/30, λ],
# fewer CG iterations on every multigrid scene at the same cost each (bench.smoothing_range;
# docs/performance.md, branch free2).
SMOOTHING_RANGE = 15.0
LAMBDA_MARGIN = 1.1      # above the estimated λ_max of D₀⁻¹A₀, for rotations and the estimate's error
TUNINGS = 4              # settings of dt and damping whose set-up a multigrid keeps (Multigrid.retune)


def coarse_grid(points: np.ndarray, target_nodes: int):
    """A box grid over the points' bounding box with at most about `target_nodes` nodes."""
    lo, size = points.min(axis=0), np.ptp(points, axis=0)
    spacing = (np.prod(size) / target_nodes) ** (1.0 / 3.0)
    while True:
        cells = np.maximum(1, np.round(size / spacing)).astype(int)
        if np.prod(cells + 1) <= target_nodes or cells.max() == 1:
            return box(size=size, cells=cells, origin=lo)
        spacing *= 1.05


# The multigrid's members of a step's argpack (tissue.solver.step_kernels.STEP): coarse_count
# [coarse nodes]; coefficients: θ, then (ρₖρₖ₋₁, 2ρₖ/δ) per Chebyshev step.
MULTIGRID_MEMBERS = ("coarse_count", "nodes", "weights", "fine_offsets", "fine_entries", "coarse_inverse", "nodal_R",
                     "res", "d", "rc", "ec", "coefficients")


def chebyshev_coefficients(lam_max: float, degree: int):
    """θ and, for the steps k = 1..degree-1, (ρₖρₖ₋₁, 2ρₖ/δ) of the Chebyshev iteration on
    [lam_max/SMOOTHING_RANGE, lam_max] (Saad, Iterative Methods, Alg. 12.1)."""
    lo = lam_max / SMOOTHING_RANGE
    theta, delta = 0.5 * (lam_max + lo), 0.5 * (lam_max - lo)
    sigma = theta / delta
    rho, steps = 1.0 / sigma, []
    for _ in range(degree - 1):
        rho_next = 1.0 / (2.0 * sigma - rho)
        steps.append((rho_next * rho, 2.0 * rho_next / delta))
        rho = rho_next
    return theta, steps


def largest_eigenvalue(A: sp.spmatrix) -> float:
    """λ_max of D⁻¹A (D: 3×3 diagonal blocks), as that of the symmetric L⁻¹ A L⁻ᵀ (D = L Lᵀ)."""
    n = A.shape[0] // 3
    coo = A.tocoo()
    own = coo.row // 3 == coo.col // 3
    D = np.zeros((n, 3, 3))
    D[coo.row[own] // 3, coo.row[own] % 3, coo.col[own] % 3] = coo.data[own]
    L_inv = sp.block_diag(list(np.linalg.inv(np.linalg.cholesky(D))), format="csr")
    S = (L_inv @ A @ L_inv.T).tocsr()
    # A fixed start vector: ARPACK's default is random, and the estimate then differs from build to
    # build in its last digits (two solvers of one body would smooth differently).
    start = np.ones(S.shape[0])
    return float(spla.eigsh(S, k=1, which="LA", tol=1e-3, v0=start, return_eigenvectors=False)[0])


def _spd_inverse(A: np.ndarray) -> np.ndarray:
    """A⁻¹ by Cholesky; where A is only semi-definite (on a small or thin body several coarse
    nodes can span the same few fine nodes, so P loses rank), the pseudo-inverse, which keeps the
    coarse correction symmetric positive semi-definite and the V-cycle a valid preconditioner."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(A), np.eye(len(A)))
    except np.linalg.LinAlgError:
        values, vectors = scipy.linalg.eigh(A)
        kept = values > 1e-12 * values.max()
        return (vectors[:, kept] / values[kept]) @ vectors[:, kept].T


class Multigrid:
    """The two-level preconditioner of one ImplicitEuler (its assembled matrix, block-diagonal
    inverse and held nodes). `apply` is a Taichi function for the solver's kernels; `rebuild()`
    redoes the set-up (numpy and scipy, no compilation) after the model or held nodes change,
    `retune()` its parts that depend on dt and the damping after those change."""

    def __init__(self, solver):
        self.solver = solver
        self.rebuild()

    def rebuild(self) -> None:
        solver = self.solver
        model, cg = solver.model, solver.cg
        mesh, n = model.mesh(), model.n_nodes
        coarse_nodes = cg.coarse_nodes if cg.coarse_nodes is not None else max(8, round(2.5 * math.sqrt(n)))
        # By default the dense coarse product, (3 · 2.5 √n)² ≈ 56 n multiply-adds, stays under
        # the ~135 n of a product with the fine matrix.
        grid = coarse_grid(mesh.points, coarse_nodes)
        embedding = EmbeddedSurface(mesh.points, np.zeros((0, 3), dtype=np.int64), grid.points, grid.tets)
        weights = np.where(np.abs(embedding.weights) > 1e-12, embedding.weights, 0.0)
        weights[model.held != 0] = 0.0        # P's rows at held (and detached) nodes are zero
        used = np.unique(embedding.nodes[weights != 0])
        nc = self.n_coarse = len(used)
        coarse = np.searchsorted(used, embedding.nodes)          # renumbered; 0 where the weight is 0
        coarse[weights == 0] = 0
        self.coarse_points = grid.points[used]
        rows = np.repeat(np.arange(n), 4)
        self._P = sp.kron(sp.csr_matrix((weights.ravel(), (rows, coarse.ravel())), shape=(n, nc)), sp.eye(3),
                          format="csr")
        # Coarse node -> its (4 fine node + corner) entries of nonzero weight, for the restriction.
        entries = np.flatnonzero(weights.ravel())
        entries = entries[np.argsort(coarse.ravel()[entries], kind="stable")]
        offsets = np.zeros(nc + 1, dtype=np.int32)
        np.cumsum(np.bincount(coarse.ravel()[entries], minlength=nc), out=offsets[1:])

        np_real = real_numpy()
        capacity = model.node_capacity      # nodal arrays sized as the solver's state
        padded_nodes = np.zeros((capacity, 4), dtype=np.int32)
        padded_nodes[:n] = coarse
        padded_weights = np.zeros((capacity, 4), dtype=np_real)
        padded_weights[:n] = weights
        arrays = _arrays(capacity, capacity, nc, len(entries), 1 + 2 * (cg.smoothing_degree - 1))
        arrays["coarse_count"].from_numpy(np.array([nc], dtype=np.int32))
        arrays["nodes"].from_numpy(padded_nodes)
        arrays["weights"].from_numpy(padded_weights)
        arrays["fine_offsets"].from_numpy(offsets)
        if len(entries):
            arrays["fine_entries"].from_numpy(entries.astype(np.int32))
        arrays["nodal_R"].from_numpy(np.tile(np.eye(3, dtype=np_real), (capacity, 1, 1)))
        self.arrays = arrays
        self._rotations_of = None      # (FEM rotation writes, tolerance) nodal_R was computed at
        self._io = [ti.ndarray(ti.types.vector(3, backend.current().real), capacity) for _ in range(2)]
        self._tunings = {}
        self.retune()

    def retune(self) -> None:
        """The parts of the set-up made from the rest matrix A₀ at the solver's dt and damping: the
        Chebyshev coefficients (from λ_max(D₀⁻¹A₀)) and the coarse inverse (Pᵀ A₀ P)⁻¹. Each
        setting's are kept until the next rebuild (at most TUNINGS of them): the energy check's
        halved steps (tissue.solver.step_control) go to dt/2 and back, and making A₀ and the
        coarse inverse again each time was most of a rejected step's cost."""
        solver = self.solver
        key = solver.rest_key()
        if key not in self._tunings:
            if len(self._tunings) == TUNINGS:
                del self._tunings[next(iter(self._tunings))]        # the oldest
            self._tunings[key] = self._tuning(solver.rest_matrix())
        self.theta, self.steps, coarse_inverse = self._tunings[key]
        np_real = real_numpy()
        # dof 3c + d of coarse node c, as P's columns
        self.arrays["coarse_inverse"].from_numpy(coarse_inverse.astype(np_real))
        self.arrays["coefficients"].from_numpy(np.array([self.theta] + [c for step in self.steps for c in step],
                                                        dtype=np_real))

    def _tuning(self, A0: sp.spmatrix):
        """(θ, the Chebyshev steps, the coarse inverse) of the rest matrix A0."""
        linked = np.repeat(self.solver.model.mass > 0, 3)            # detached nodes have empty rows
        theta, steps = chebyshev_coefficients(LAMBDA_MARGIN * largest_eigenvalue(A0[linked][:, linked]),
                                              self.solver.cg.smoothing_degree)
        # The rest Galerkin operator Pᵀ A₀ P, inverted on the coarse dofs that keep a nonzero column.
        Ac = (self._P.T @ A0 @ self._P).toarray()
        active = np.flatnonzero(np.diag(Ac) > 1e-12 * np.abs(np.diag(Ac)).max())
        C = np.zeros_like(Ac)
        C[np.ix_(active, active)] = _spd_inverse(Ac[np.ix_(active, active)])
        return theta, steps, 0.5 * (C + C.T)

    def rotations_computed(self, tol: float) -> None:
        """The solver's step (its prepare_step counted in the FEM's rotation_writes) just wrote
        nodal_R from the element rotations it wrote."""
        self._rotations_of = (self.solver.fem.rotation_writes, tol)

    def nodal_rotations(self, tol: float):
        """nodal_R (an ndarray of the node capacity) where it is the nodal rotations of the FEM's
        element rotations as they are now, at `tol`; else None (none computed since the last
        rebuild, or the element rotations written since)."""
        if self._rotations_of != (self.solver.fem.rotation_writes, tol):
            return None
        return self.arrays["nodal_R"]

    # ---- standalone launch (tests) -----------------------------------------------------------

    def apply_numpy(self, r: np.ndarray) -> np.ndarray:
        """B r for residuals r (n, 3), with the matrix and rotations of the solver's last step."""
        src, dst = self._io
        n = self.solver.model.n_nodes
        padded = np.zeros((src.shape[0], 3), dtype=real_numpy())
        padded[:n] = r
        src.from_numpy(padded)
        from .step_kernels import apply_preconditioner   # (it imports this module)
        apply_preconditioner(self.solver._step_pack(), self.solver.scheme, src, dst)
        return dst.to_numpy()[:n].astype(np.float64)


class BlockJacobi:
    """Block-Jacobi, z = D⁻¹ r, as the V-cycle's degenerate case for the serial step: no coarse
    space (the cycle stops after its first smoothing) and a smoother of degree 1 with θ = 1, so z
    is D⁻¹ r to the bit. The serial step's kernel instance is then the one the multigrid schemes
    compile (a kernel's compilation is most of a warm start): its arrays have the multigrid's
    types, a single entry where the cycle does not reach."""

    def __init__(self, solver):
        self.solver = solver
        self._capacity = None
        self.rebuild()

    def rebuild(self) -> None:
        capacity = self.solver.model.node_capacity      # the smoother's scratch, sized as the state
        if capacity != self._capacity:
            self.arrays = _arrays(1, capacity, 0, 0, 1)
            self.arrays["coarse_count"].from_numpy(np.zeros(1, dtype=np.int32))
            self.arrays["coefficients"].from_numpy(np.ones(1, dtype=real_numpy()))
            self._capacity = capacity

    def retune(self) -> None:
        """Nothing to redo: block-Jacobi does not depend on dt or the damping."""

    def rotations_computed(self, tol: float) -> None:
        """Nothing to note: without a coarse space the cycle computes no nodal rotations."""

    def nodal_rotations(self, tol: float):
        """None: the step computed no nodal rotations (Multigrid.nodal_rotations)."""
        return None


def _arrays(fine: int, scratch: int, coarse: int, entries: int, coefficients: int) -> dict:
    """The multigrid's members of a step's argpack, unfilled: `fine` rows of P and of the nodal
    rotations, `scratch` of the smoother's, `coarse` coarse nodes, `entries` of the restriction,
    `coefficients` (at least one entry each). Their types key the kernel's instance."""
    real = backend.current().real
    vec3, mat3, vec4 = ti.types.vector(3, real), ti.types.matrix(3, 3, real), ti.types.vector(4, real)
    dofs = max(1, 3 * coarse)
    return dict(coarse_count=ti.ndarray(ti.i32, 1), nodes=ti.ndarray(ti.types.vector(4, ti.i32), fine),
                weights=ti.ndarray(vec4, fine), fine_offsets=ti.ndarray(ti.i32, coarse + 1),
                fine_entries=ti.ndarray(ti.i32, max(1, entries)), coarse_inverse=ti.ndarray(real, (dofs, dofs)),
                nodal_R=ti.ndarray(mat3, fine), res=ti.ndarray(vec3, scratch), d=ti.ndarray(vec3, scratch),
                rc=ti.ndarray(real, dofs), ec=ti.ndarray(real, dofs), coefficients=ti.ndarray(real, coefficients))


# ---- Taichi functions, called at the top level of the solver's kernels over its argpack `k` -------


@ti.func
def update_rotations(k: ti.template(), tol):
    """The nodal rotations the coarse correction turns by (none without a coarse space)."""
    for v in range(k.counts[0]):
        if _coarse(k):
            k.nodal_R[v] = nodal_rotation(k.R, k.valence, k.incidence, v, tol)


@ti.func
def _coarse(k: ti.template()):
    return k.coarse_count[0] > 0


@ti.func
def _running(k: ti.template()):
    return k.scalars[DONE] == 0


@ti.func
def _residual(k: ti.template(), o: ti.template(), r: ti.template(), z: ti.template()):
    """res = r - A z, after `multiply(z)`."""
    mass_factor, stiffness_factor = factors(k)
    for v in range(k.counts[0]):
        if _running(k):
            k.res[v] = r[v] - operator_row(k, o, v, z, mass_factor, stiffness_factor)


@ti.func
def _smooth(k: ti.template(), o: ti.template(), r: ti.template(), z: ti.template(), from_zero):
    """z += S res (Chebyshev in D⁻¹A): from zero (known at compile or run time), res = r and z = S r;
    else from res = r - A z, which one thread takes here, in the same pass over the nodes (after
    `multiply(z)`: a node's row reads only its own z), and the parallel rows layout, whose rows
    read the neighbours' z, in a pass of its own before (_residual). res and d are kept only for the
    Chebyshev steps that follow (block-Jacobi, of degree 1, has none)."""
    mass_factor, stiffness_factor = factors(k)
    chebyshev = k.coefficients.shape[0] > 1
    for v in range(k.counts[0]):
        if _running(k):
            res = r[v]
            if not from_zero:
                if ti.static(o.serial):
                    res = r[v] - operator_row(k, o, v, z, mass_factor, stiffness_factor)
                else:
                    res = k.res[v]
            d = (k.block_inverse[v] @ res) / k.coefficients[0]
            if chebyshev:
                k.res[v] = res
                k.d[v] = d
            if from_zero:
                z[v] = d
            else:
                z[v] = z[v] + d
    if ti.static(o.serial):   # one thread: a runtime loop, the step inlined once, its degree read
        for step in range((k.coefficients.shape[0] - 1) // 2):
            _chebyshev_step(k, o, z, step)
    else:
        for step in ti.static(range(o.smoothing_degree - 1)):
            _chebyshev_step(k, o, z, step)


@ti.func
def _chebyshev_step(k: ti.template(), o: ti.template(), z: ti.template(), step):
    """res -= A d, then d and z: node by node in one pass where one thread runs the cycle (multiply
    took A d whole: a node's row reads only its own d); in two on the parallel rows layout, whose
    rows read the neighbours' d."""
    multiply(k, o, k.d)
    mass_factor, stiffness_factor = factors(k)
    for v in range(k.counts[0]):
        if _running(k):
            k.res[v] = k.res[v] - operator_row(k, o, v, k.d, mass_factor, stiffness_factor)
            if ti.static(o.serial):
                _chebyshev_update(k, z, step, v)
    if ti.static(not o.serial):
        for v in range(k.counts[0]):
            if _running(k):
                _chebyshev_update(k, z, step, v)


@ti.func
def _chebyshev_update(k: ti.template(), z: ti.template(), step, v):
    d = k.coefficients[1 + 2 * step] * k.d[v] + k.coefficients[2 + 2 * step] * (k.block_inverse[v] @ k.res[v])
    k.d[v] = d
    z[v] = z[v] + d


@ti.func
def _coarse_correction(k: ti.template(), o: ti.template(), r: ti.template(), z: ti.template()):
    """z += R P A_c⁻¹ Pᵀ Rᵀ (r - A z), after `multiply(z)`. The residual is turned by Rᵀ node by node
    as it is taken (into d, which the next smoothing starts afresh), once rather than at each of
    the node's up to 4 coarse nodes. The coarse vectors are flat (coarse node c's dofs at 3c,
    3c+1, 3c+2), so that the dense product is one scalar dot product per row of A_c⁻¹, 3·nc rows
    to share out."""
    mass_factor, stiffness_factor = factors(k)
    for v in range(k.counts[0]):
        if _running(k):
            k.d[v] = k.nodal_R[v].transpose() @ (r[v] - operator_row(k, o, v, z, mass_factor, stiffness_factor))
    for c in range(k.coarse_count[0]):  # restriction: a gather over the fine nodes around c
        if _running(k):
            s = ti.Vector([0.0, 0.0, 0.0])
            for j in range(k.fine_offsets[c], k.fine_offsets[c + 1]):
                v, corner = k.fine_entries[j] // 4, k.fine_entries[j] % 4
                s += k.weights[v][corner] * k.d[v]
            for d in ti.static(range(3)):
                k.rc[3 * c + d] = s[d]
    for i in range(3 * k.coarse_count[0]):
        if _running(k):
            s = 0.0
            for j in range(3 * k.coarse_count[0]):
                s += k.coarse_inverse[i, j] * k.rc[j]
            k.ec[i] = s
    for v in range(k.counts[0]):  # prolongation
        if _running(k):
            s = ti.Vector([0.0, 0.0, 0.0])
            for corner in ti.static(range(4)):
                c = k.nodes[v][corner]
                s += k.weights[v][corner] * ti.Vector([k.ec[3 * c], k.ec[3 * c + 1], k.ec[3 * c + 2]])
            z[v] = z[v] + k.nodal_R[v] @ s


@ti.func
def apply(k: ti.template(), o: ti.template(), r: ti.template(), z: ti.template()):
    """z = B r, one symmetric V-cycle: smooth, residual, coarse correction, residual, smooth; every
    loop is skipped once the solver's CG has converged."""
    if ti.static(o.serial):
        # One thread: the stages as a runtime loop, so that each product with A is inlined once
        # (a kernel's size is what its compilation costs in every process).
        # Skipped whole once converged: its loops would skip their nodes, but not the products.
        # Without a coarse space (BlockJacobi) the cycle is its first smoothing.
        for stage in range(3):
            if not _running(k) or (stage == 1 and not _coarse(k)):
                break
            if stage == 0:
                _smooth(k, o, r, z, True)
            else:
                multiply(k, o, z)       # for the residual r - A z
                if stage == 1:
                    _coarse_correction(k, o, r, z)
                else:
                    _smooth(k, o, r, z, False)
    else:   # parallel loops stay at the kernel's top level
        _smooth(k, o, r, z, True)
        multiply(k, o, z)
        _coarse_correction(k, o, r, z)
        multiply(k, o, z)
        _residual(k, o, r, z)
        _smooth(k, o, r, z, False)
