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
small on [λ/30, λ], λ = 1.1 λ_max(D₀⁻¹A₀) estimated once at rest (a rotation of the body leaves
the spectrum of D⁻¹A unchanged; removing fixed dofs only lowers λ_max). Cost per application:
2·degree products with A, a restriction and a prolongation over 4 coarse nodes per fine node,
and one dense product with A_c⁻¹ (3·coarse nodes)².
"""

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import taichi as ti

from .. import backend
from ..fem.corotational import int_field, nodal_rotation
from ..mesh import box
from ..mesh.embedding import EmbeddedSurface
from .reference import rest_matrix

SMOOTHING_RANGE = 30.0   # Chebyshev targets [λ/30, λ]: the part of the spectrum the coarse space misses
LAMBDA_MARGIN = 1.1      # above the estimated λ_max of D₀⁻¹A₀, for rotations and the estimate's error


def coarse_grid(points: np.ndarray, target_nodes: int):
    """A box grid over the points' bounding box with at most about `target_nodes` nodes."""
    lo, size = points.min(axis=0), np.ptp(points, axis=0)
    spacing = (np.prod(size) / target_nodes) ** (1.0 / 3.0)
    while True:
        cells = np.maximum(1, np.round(size / spacing)).astype(int)
        if np.prod(cells + 1) <= target_nodes or cells.max() == 1:
            return box(size=size, cells=cells, origin=lo)
        spacing *= 1.05


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
    return float(spla.eigsh(S, k=1, which="LA", tol=1e-3, return_eigenvectors=False)[0])


@ti.data_oriented
class Multigrid:
    """The two-level preconditioner of one ImplicitEuler (its assembled matrix, block-diagonal
    inverse and fixed nodes). `apply` is a Taichi function for the solver's kernels."""

    def __init__(self, solver, coarse_nodes: int, degree: int):
        fem = solver.fem
        mesh, n = fem.mesh, fem.n_nodes
        real = fem.R.dtype
        self.solver, self.n_nodes = solver, n
        self._np = np.float64 if real == ti.f64 else np.float32
        grid = coarse_grid(mesh.points, coarse_nodes)
        embedding = EmbeddedSurface(mesh.points, np.zeros((0, 3), dtype=np.int64), grid.points, grid.tets)
        weights = np.where(np.abs(embedding.weights) > 1e-12, embedding.weights, 0.0)
        used = np.unique(embedding.nodes[weights != 0])
        self.n_coarse = len(used)
        coarse = np.searchsorted(used, embedding.nodes)          # renumbered; 0 where the weight is 0
        coarse[weights == 0] = 0
        self.coarse_points = grid.points[used]
        self._weights, self._coarse = weights, coarse
        self.A0 = rest_matrix(mesh, fem.material, solver.dt, solver.rayleigh_mass, solver.rayleigh_stiffness)
        self.theta, self.steps = chebyshev_coefficients(LAMBDA_MARGIN * largest_eigenvalue(self.A0), degree)

        nc = self.n_coarse
        # Coarse node -> its (4 fine node + corner) entries of nonzero weight, for the restriction.
        entries = np.flatnonzero(weights.ravel())
        entries = entries[np.argsort(coarse.ravel()[entries], kind="stable")]
        offsets = np.zeros(nc + 1, dtype=np.int32)
        np.cumsum(np.bincount(coarse.ravel()[entries], minlength=nc), out=offsets[1:])
        with backend.fields_of(self):
            self.nodes = int_field(n, 4)
            self.weights = ti.Vector.field(4, real, n)
            self.fine_offsets = int_field(nc + 1)
            self.fine_entries = int_field(len(entries))
            self.coarse_inverse = ti.Matrix.field(3, 3, real, (nc, nc))
            self.R = ti.Matrix.field(3, 3, real, n)                  # nodal rotations
            self.res = ti.Vector.field(3, real, n)
            self.d = ti.Vector.field(3, real, n)
            self.rc = ti.Vector.field(3, real, nc)
            self.ec = ti.Vector.field(3, real, nc)
            self._io = [ti.Vector.field(3, real, n) for _ in range(2)] + [ti.field(real, 1)]
        self.nodes.from_numpy(coarse.astype(np.int32))
        self.fine_offsets.from_numpy(offsets)
        self.fine_entries.from_numpy(entries.astype(np.int32))
        self.R.from_numpy(np.tile(np.eye(3, dtype=self._np), (n, 1, 1)))
        self._tol = fem.rotation_tolerance

    def set_fixed(self, mask: np.ndarray) -> None:
        """Zero P's rows at the fixed nodes and invert the rest Galerkin operator Pᵀ A₀ P on the
        coarse dofs that keep a nonzero column."""
        n, nc = self.n_nodes, self.n_coarse
        weights = np.where(mask[:, None] != 0, 0.0, self._weights)
        rows = np.repeat(np.arange(n), 4)
        P = sp.kron(sp.csr_matrix((weights.ravel(), (rows, self._coarse.ravel())), shape=(n, nc)),
                    sp.eye(3), format="csr")
        Ac = (P.T @ self.A0 @ P).toarray()
        active = np.flatnonzero(np.diag(Ac) > 1e-12 * np.abs(np.diag(Ac)).max())
        C = np.zeros_like(Ac)
        C[np.ix_(active, active)] = scipy.linalg.cho_solve(
            scipy.linalg.cho_factor(Ac[np.ix_(active, active)]), np.eye(len(active)))
        C = 0.5 * (C + C.T)
        self.weights.from_numpy(weights.astype(self._np))
        self.coarse_inverse.from_numpy(C.reshape(nc, 3, nc, 3).transpose(0, 2, 1, 3).astype(self._np))

    # ---- Taichi functions, called at the top level of the solver's kernels ---------------------

    @ti.func
    def update_rotations(self):
        fem = self.solver.fem
        for v in range(self.n_nodes):
            self.R[v] = nodal_rotation(fem.R, fem.incidence_offsets, fem.incidence, v, self._tol)

    @ti.func
    def _residual(self, r, z, flags: ti.template(), slot: ti.template()):
        self.solver.multiply(z)
        for v in range(self.n_nodes):  # res = r - A z
            if flags[slot] == 0:
                self.res[v] = r[v] - self.solver.operator_row(v, z)

    @ti.func
    def _smooth(self, r, z, flags: ti.template(), slot: ti.template(), from_zero: ti.template()):
        """z += S res (Chebyshev in D⁻¹A); from zero, res = r and z = S r."""
        for v in range(self.n_nodes):
            if flags[slot] == 0:
                if ti.static(from_zero):
                    self.res[v] = r[v]
                    z[v] = ti.Vector([0.0, 0.0, 0.0])
                d = (self.solver.block_inverse[v] @ self.res[v]) / self.theta
                self.d[v] = d
                z[v] = z[v] + d
        for k in ti.static(range(len(self.steps))):
            self.solver.multiply(self.d)
            for v in range(self.n_nodes):
                if flags[slot] == 0:
                    self.res[v] = self.res[v] - self.solver.operator_row(v, self.d)
            for v in range(self.n_nodes):
                if flags[slot] == 0:
                    d = self.steps[k][0] * self.d[v] + self.steps[k][1] * (self.solver.block_inverse[v] @ self.res[v])
                    self.d[v] = d
                    z[v] = z[v] + d

    @ti.func
    def _coarse_correction(self, z, flags: ti.template(), slot: ti.template()):
        """z += R P A_c⁻¹ Pᵀ Rᵀ res."""
        for c in range(self.n_coarse):  # restriction: a gather over the fine nodes around c
            if flags[slot] == 0:
                s = ti.Vector([0.0, 0.0, 0.0])
                for k in range(self.fine_offsets[c], self.fine_offsets[c + 1]):
                    v, corner = self.fine_entries[k] // 4, self.fine_entries[k] % 4
                    s += self.weights[v][corner] * (self.R[v].transpose() @ self.res[v])
                self.rc[c] = s
        for c in range(self.n_coarse):
            if flags[slot] == 0:
                s = ti.Vector([0.0, 0.0, 0.0])
                for j in range(self.n_coarse):
                    s += self.coarse_inverse[c, j] @ self.rc[j]
                self.ec[c] = s
        for v in range(self.n_nodes):  # prolongation
            if flags[slot] == 0:
                s = ti.Vector([0.0, 0.0, 0.0])
                for corner in ti.static(range(4)):
                    s += self.weights[v][corner] * self.ec[self.nodes[v][corner]]
                z[v] = z[v] + self.R[v] @ s

    @ti.func
    def apply(self, r, z, flags: ti.template(), slot: ti.template()):
        """z = B r, one symmetric V-cycle; every loop is skipped while flags[slot] ≠ 0 (the
        solver's "converged" flag)."""
        self._smooth(r, z, flags, slot, True)
        self._residual(r, z, flags, slot)
        self._coarse_correction(z, flags, slot)
        self._residual(r, z, flags, slot)
        self._smooth(r, z, flags, slot, False)

    # ---- standalone launch (tests) -----------------------------------------------------------

    @ti.kernel
    def _apply_kernel(self, r: ti.template(), z: ti.template(), flags: ti.template()):
        self.apply(r, z, flags, 0)

    def apply_numpy(self, r: np.ndarray) -> np.ndarray:
        """B r for residuals r (n, 3), with the matrix and rotations of the solver's last step."""
        src, dst, flags = self._io
        src.from_numpy(np.asarray(r, dtype=self._np))
        self._apply_kernel(src, dst, flags)
        return dst.to_numpy().astype(np.float64)

