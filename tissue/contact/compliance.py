"""Compliance of the soft bodies: the Delassus operator W of the constraints and the corrective
motion, either by compliance warping (paper §3.2, §3.5) or exactly (the reference and baseline).

Derivation (conventions of tissue.solver.implicit_euler). The free motion solves
A dv_free = b with A = (1 + h α_M) M + (h α_K + h²) K, then v_free = v + dv_free and
x_free = x + h v_free. The constraint reactions λ are IMPULSES (N·s) along the rows of H; they
enter the same linear system as A dv = b + Hᵀ λ (the force they stand for is Hᵀ λ / h). So

    dv_c = v⁺ - v_free = A⁻¹ Hᵀ λ,        x⁺ - x_free = h dv_c = h A⁻¹ Hᵀ λ.

The constraints are on POSITIONS: δ(x⁺) ≈ δ_free + H (x⁺ - x_free) (gaps, tangential displacement
over the step, attachment errors, in metres; see constraints.py), hence

    δ = δ_free + W λ,     W = h H A⁻¹ Hᵀ = H C Hᵀ,   C = h A⁻¹    (paper eqs. 10, 14),

summed over the bodies a row touches; rigid obstacles add nothing (zero compliance).
The corrective motion is x⁺ = x_free + h A⁻¹ Hᵀ λ with v⁺ = v_free + (x⁺ - x_free) / h, which
keeps x⁺ = x + h v⁺, the solver's own relation, so the next step starts consistent.

Warping. A = R A₀ Rᵀ would hold exactly if every element turned by the same R (A₀: the rest
matrix, R block-diagonal); with nodal rotations Rᵥ (the polar factor of the sum of the incident
elements' rotations, i.e. their orthonormalised average) it is the paper's approximation:

    W ≈ h (H R) A₀⁻¹ (H R)ᵀ,     x⁺ ≈ x_free + R h A₀⁻¹ (H R)ᵀ λ.

A₀⁻¹ is computed once, dense, from the assembled sparse A₀ (tissue.solver.reference) with the
body's dt, damping and fixed nodes (their rows and columns are zero: fixed nodes do not move). The
same approximate operator builds W and applies the correction, so δ = δ_free + W λ holds exactly
for what is applied; the approximation only changes which λ is found. Kernels: (1) Hr = H R, a
thread per stored block; U = A₀⁻¹ Hrᵀ, a thread per entry (dof, row); (2) W += h Hr U, a thread
per entry of W; the rows' blocks are read through JDS. Going through U rather than summing
Hr(i,·) A₀⁻¹ Hr(j,·)ᵀ in each entry of W needs (3n + rows) 3b instead of rows 9b²
multiplications per row (b blocks per row; about 2/3 as many for the liver's 350 rows, b ≈ 2.2,
fewer the more rows), and the correction is then one product, dx = R h U λ (a thread per node).

Exact. W = h H A⁻¹ Hᵀ with A the matrix of this step's free motion (assembled where it linearised,
at x_prev = x_free - h v_free: the solver's own stiffness blocks, or the numpy reference),
factorised with scipy's sparse LU each step; the correction uses the same factorisation. This is
the reference for the warping error and the paper's "direct inversion" baseline.
"""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem.corotational import polar_rotation
from ..solver.reference import free_dofs, linearise, rest_compliance
from .constraints import ConstraintRows, JaggedDiagonal


@ti.kernel
def _nodal_rotations(Re: ti.template(), offsets: ti.template(), incidence: ti.template(),
                     out: ti.template(), tol: float):
    for v in out:
        S = ti.Matrix.zero(float, 3, 3)
        for k in range(offsets[v], offsets[v + 1]):
            S += Re[incidence[k] // 4]
        out[v] = polar_rotation(S, tol)


@ti.kernel
def _rotate_rows(value: ti.types.ndarray(), node: ti.types.ndarray(), R: ti.template(),
                 hr: ti.types.ndarray()):
    """Kernel 1: Hr = H R, block by block (a 1×3 row block times the node's 3×3 rotation)."""
    for e in range(node.shape[0]):
        h = ti.Vector([value[e, 0], value[e, 1], value[e, 2]])
        r = R[node[e]].transpose() @ h
        for c in ti.static(range(3)):
            hr[e, c] = r[c]


@ti.kernel
def _compliance_rows(C0: ti.types.ndarray(), count: ti.types.ndarray(), jd_ptr: ti.types.ndarray(),
                     node: ti.types.ndarray(), hr: ti.types.ndarray(), Ut: ti.types.ndarray()):
    """Uᵀ = Hr A₀⁻¹ (active rows × 3n), a thread per entry, the dof fastest: A₀⁻¹ is symmetric, so
    each thread reads rows of it and neighbouring threads neighbouring entries."""
    for i, k in ti.ndrange(Ut.shape[0], Ut.shape[1]):
        s = 0.0
        for l in range(count[i]):
            e = jd_ptr[l] + i
            b = 3 * node[e]
            for c in ti.static(range(3)):
                s += hr[e, c] * C0[b + c, k]
        Ut[i, k] = s


@ti.kernel
def _add_delassus(perm: ti.types.ndarray(), count: ti.types.ndarray(), jd_ptr: ti.types.ndarray(),
                  node: ti.types.ndarray(), hr: ti.types.ndarray(), Ut: ti.types.ndarray(), h: float,
                  W: ti.types.ndarray()):
    """Kernel 2: W[perm i, perm j] += h (Hr U)(i, j), a thread per entry of W (the row of Uᵀ it
    reads is shared by neighbouring threads); W is symmetric, so the upper triangle is computed and
    mirrored."""
    for j, i in ti.ndrange(Ut.shape[0], Ut.shape[0]):
        if i >= j:
            s = 0.0
            for l in range(count[i]):
                e = jd_ptr[l] + i
                a = 3 * node[e]
                for c in ti.static(range(3)):
                    s += hr[e, c] * Ut[j, a + c]
            W[perm[i], perm[j]] += h * s
            if i != j:
                W[perm[j], perm[i]] += h * s


@ti.kernel
def _correct(Ut: ti.types.ndarray(), perm: ti.types.ndarray(), lam: ti.types.ndarray(), R: ti.template(),
             x: ti.template(), v: ti.template(), h: float):
    """dx = R h A₀⁻¹ (H R)ᵀ λ = R h U λ, a thread per node; x += dx, v += dx / h."""
    for k in x:
        s = ti.Vector([0.0, 0.0, 0.0])
        for i in range(Ut.shape[0]):
            li = lam[perm[i]]
            for c in ti.static(range(3)):
                s[c] += Ut[i, 3 * k + c] * li
        dx = h * (R[k] @ s)
        x[k] += dx
        v[k] += dx / h


class WarpedCompliance:
    """One soft body's rest compliance A₀⁻¹ (dense, on the device) and nodal rotations."""

    def __init__(self, solver):
        fem = solver.fem
        be = backend.current()
        self.solver, self.real = solver, be.real
        self._np = np.float64 if be.real == ti.f64 else np.float32
        C0 = rest_compliance(fem.mesh, fem.material, solver.dt, fixed=solver.fixed_nodes,
                             rayleigh_mass=solver.rayleigh_mass, rayleigh_stiffness=solver.rayleigh_stiffness)
        self.C0_host = 0.5 * (C0 + C0.T)          # symmetric to round-off; the kernels rely on it
        self.C0 = ti.ndarray(dtype=self.real, shape=self.C0_host.shape)
        self.C0.from_numpy(self.C0_host.astype(self._np))
        self.R = ti.Matrix.field(3, 3, self.real, fem.n_nodes)
        self._tol = fem.rotation_tolerance

    def update_rotations(self) -> None:
        """Nodal rotations from the element rotations of the last free motion."""
        fem = self.solver.fem
        _nodal_rotations(fem.R, fem.incidence_offsets, fem.incidence, self.R, self._tol)

    def nodal_rotations(self) -> np.ndarray:
        return self.R.to_numpy().astype(np.float64)

    def prepare(self, jds: JaggedDiagonal) -> None:
        """Kernel 1 (Hr = H R) and U = A₀⁻¹ Hrᵀ for this step's H."""
        self.jds = jds
        self.hr = np.empty((jds.nnz, 3), dtype=self._np)
        self.Ut = np.empty((jds.n_active, self.C0.shape[0]), dtype=self._np)
        if jds.nnz:
            _rotate_rows(jds.value, jds.node, self.R, self.hr)
            _compliance_rows(self.C0, jds.count, jds.jd_ptr, jds.node, self.hr, self.Ut)

    def add_to(self, W: np.ndarray) -> None:
        """W (n_rows², the backend's float type) += h (H R) A₀⁻¹ (H R)ᵀ."""
        jds = self.jds
        if jds.n_active:
            _add_delassus(jds.perm, jds.count, jds.jd_ptr, jds.node, self.hr, self.Ut, self.solver.dt, W)

    def correct(self, lam: np.ndarray) -> None:
        """x += R h A₀⁻¹ (H R)ᵀ λ and v += that / h, in the solver's fields."""
        jds = self.jds
        if jds.n_active:
            _correct(self.Ut, jds.perm, lam.astype(self._np), self.R, self.solver.x, self.solver.v, self.solver.dt)


class ExactCompliance:
    """One soft body's exact compliance h A⁻¹ from a sparse LU of the current matrix, each step."""

    def __init__(self, solver, assembly: str = "solver"):
        if assembly not in ("solver", "reference"):
            raise TissueError(f"assembly: unknown {assembly!r}; expected 'solver' or 'reference'")
        self.solver, self.assembly = solver, assembly
        fem = solver.fem
        self.free = free_dofs(fem.n_nodes, solver.fixed_nodes)

    def factorise(self) -> None:
        """Factorise A where the free motion linearised: the solver's own assembled stiffness
        blocks when it keeps them (operator "assembled") and `assembly` is "solver", else the
        numpy reference assembly at x_prev = x_free - h v_free (also right after a set_state)."""
        s, fem = self.solver, self.solver.fem
        matrix = getattr(s, "matrix", None)
        if matrix is not None and self.assembly == "solver":
            n3 = 3 * fem.n_nodes
            K = sp.bsr_matrix((matrix.blocks.to_numpy().astype(np.float64), matrix.columns.to_numpy(),
                               matrix.row_offsets.to_numpy()), shape=(n3, n3)).tocsr()
            mass = np.repeat(fem.mass.to_numpy().astype(np.float64), 3)
            A = sp.diags(s.mass_factor * mass) + s.stiffness_factor * K
        else:
            v = s.velocities()
            A = linearise(fem.mesh, fem.material, s.positions() - s.dt * v, v, s.dt, rayleigh_mass=s.rayleigh_mass,
                          rayleigh_stiffness=s.rayleigh_stiffness, rotation=fem.rotation).A
        A = A.tocsr()
        self.lu = spla.splu(A[self.free][:, self.free].tocsc(), permc_spec="MMD_AT_PLUS_A")

    def prepare(self, rows: ConstraintRows, body: int) -> None:
        H = rows.body_matrix(body, self.solver.fem.n_nodes)[:, self.free]
        self.active = np.flatnonzero(H.getnnz(axis=1))
        self.H = H[self.active]
        self.X = self.lu.solve(self.H.T.toarray()) if len(self.active) else np.zeros((len(self.free), 0))

    def add_to(self, W: np.ndarray) -> None:
        """W (numpy, n_rows²) += h H A⁻¹ Hᵀ."""
        if len(self.active):
            W[np.ix_(self.active, self.active)] += self.solver.dt * (self.H @ self.X)

    def correct(self, lam: np.ndarray) -> None:
        if not len(self.active):
            return
        s = self.solver
        dx = np.zeros(3 * s.fem.n_nodes)
        dx[self.free] = s.dt * (self.X @ lam[self.active])
        dx = dx.reshape(-1, 3)
        s.set_state(s.positions() + dx, s.velocities() + dx / s.dt)
