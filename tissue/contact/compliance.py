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

Compliance warping, the paper's approximation of W, is tissue.contact.warping's.

Exact. W = h H A⁻¹ Hᵀ with A the matrix of this step's free motion (assembled where it linearised,
at x_prev = x_free - h v_free: the solver's own stiffness blocks, or the numpy reference),
factorised once per step, as SOFA's sparse LDLᵀ does: A is symmetric positive definite, so a
sparse Cholesky factorisation with a fill-reducing order (CHOLMOD, through scikit-sparse, AMD or
METIS, whichever fills less; the analysis once per sparsity pattern, the numbers each step):
simplicial LDLᵀ for bodies up to SIMPLICIAL_DOFS free dofs, supernodal LLᵀ above (at the scenes'
sizes the simplicial factorisation and its triangular solves take about half the supernodal's
time; `bench/contact.py` times the exact stage). W needs only half a solve: with P A Pᵀ = L D Lᵀ,
H A⁻¹ Hᵀ = Yᵀ Y for Y = D^-½ L⁻¹ P Hᵀ, one forward substitution for all the columns at once; and
for fewer columns, Hᵀ = S G with S the unit vectors of the dofs the rows touch (when a contact's
three rows share fewer dofs than rows), W = h Gᵀ (Yᵀ Y) G, Y from S. The correction is one full
solve, A⁻¹ (Hᵀ λ).
Without scikit-sparse (an optional extra: Debian's libsuitesparse-dev, then pip install
tissue[cholmod]) scipy's SuperLU with the MMD order of Aᵀ + A stands in (`factorization="lu"`,
slower on the scenes' bodies; bench/contact.py measures both). This is the reference for the
warping error and the paper's "direct inversion" baseline.
"""

import numpy as np
import scipy.linalg.blas
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import taichi as ti

from ..errors import TissueError
from ..fem.model import real_numpy
from ..solver.reference import free_dofs, linearise
from .constraints import ConstraintRows

try:
    from sksparse.cholmod import analyze as _cholmod
except ImportError:          # the optional extra tissue[cholmod]; scipy's LU stands in (see above)
    _cholmod = None

FACTORIZATIONS = ("auto", "cholmod", "lu")
SIMPLICIAL_DOFS = 2500      # free dofs up to which CHOLMOD factorises simplicially (see above)


class ExactCompliance:
    """One soft body's exact compliance h A⁻¹ from a sparse factorisation of the current matrix,
    each step: CHOLMOD's Cholesky (`factorization` "cholmod"; "auto" when scikit-sparse is
    installed) or scipy's LU ("lu")."""

    def __init__(self, solver, assembly: str = "solver", factorization: str = "auto"):
        if assembly not in ("solver", "reference"):
            raise TissueError(f"assembly: unknown {assembly!r}; expected 'solver' or 'reference'")
        if factorization not in FACTORIZATIONS:
            raise TissueError(f"factorization: unknown {factorization!r}; expected one of {', '.join(FACTORIZATIONS)}")
        if factorization == "cholmod" and _cholmod is None:
            raise TissueError("factorization: 'cholmod' needs scikit-sparse (apt-get install libsuitesparse-dev, "
                              "then pip install 'tissue[cholmod]'); 'lu' uses scipy's LU instead")
        if factorization == "auto":
            factorization = "lu" if _cholmod is None else "cholmod"
        self.solver, self.assembly, self.factorization = solver, assembly, factorization
        self.follow_edits()

    def follow_edits(self) -> None:
        """The free dofs of the body's current topology, and no symbolic analysis of the old one
        (the numeric factorisation is redone every step anyway)."""
        self._symbolic, self._pattern, self._gather = None, None, None
        self.free = free_dofs(self.solver.fem.n_nodes, self.solver.fixed_nodes)

    def follow(self, compliance) -> None:
        """Nothing to follow: the exact compliance factorises the current matrix each step."""

    def factorise(self) -> None:
        """Factorise A where the free motion linearised: the solver's own assembled stiffness
        blocks when it keeps them (operator "assembled") and `assembly` is "solver", else the
        numpy reference assembly at x_prev = x_free - h v_free (also right after a set_state)."""
        s, fem = self.solver, self.solver.fem
        matrix = getattr(s, "matrix", None)
        if matrix is not None and self.assembly == "solver":
            A = self._matrix_from_blocks(matrix)
        else:
            v = s.velocities()
            A = linearise(fem.mesh, fem.material, s.positions() - s.dt * v, v, s.dt, rayleigh_mass=s.rayleigh_mass,
                          rayleigh_stiffness=s.rayleigh_stiffness, rotation=fem.rotation).A
            A = A.tocsc()[self.free][:, self.free]
        if self.factorization == "cholmod":
            # The fill-reducing order P and L's structure (CHOLMOD's analysis) once per sparsity
            # pattern, which a body keeps until its topology is edited; then only the numbers.
            pattern = (A.indptr, A.indices)
            if self._pattern is None or not all(np.array_equal(a, b) for a, b in zip(pattern, self._pattern)):
                self._ldlt = A.shape[0] <= SIMPLICIAL_DOFS       # CHOLMOD's simplicial factor is L D Lᵀ
                mode = "simplicial" if self._ldlt else "supernodal"
                self._symbolic, self._pattern = _cholmod(A, mode=mode), (A.indptr.copy(), A.indices.copy())
            self._symbolic.cholesky_inplace(A)
            self._solve = self._symbolic
        else:
            self._solve = spla.splu(A, permc_spec="MMD_AT_PLUS_A").solve

    def _matrix_from_blocks(self, matrix) -> sp.csc_matrix:
        """A = m_f M + s_f K among the free dofs, K the solver's blocks: gathered into a CSC pattern
        made once per topology (the matrix in scipy holding each entry's index into the blocks),
        where converting the blocks and slicing out the free dofs each step cost more than
        CHOLMOD's factorisation (the same numbers, in the same order of operations)."""
        s, values = self.solver, matrix.block_values()
        if self._gather is None or self._n_values != len(values):
            coded = matrix.to_scipy(np.arange(1.0, len(values) + 1.0)).tocsc()[self.free][:, self.free]
            coded.sort_indices()
            column = np.repeat(np.arange(coded.shape[1]), np.diff(coded.indptr))
            self._on_diagonal = coded.indices == column
            self._diagonal_mass = np.repeat(s.fem.model.mass, 3)[self.free][column[self._on_diagonal]]
            self._gather, self._n_values, self._csc = coded.data.astype(np.int64) - 1, len(values), coded
        data = s.stiffness_factor * values[self._gather]
        data[self._on_diagonal] += s.mass_factor * self._diagonal_mass
        return sp.csc_matrix((data, self._csc.indices, self._csc.indptr), shape=self._csc.shape)

    def prepare(self, rows: ConstraintRows, body: int) -> None:
        """B = Sᵀ A⁻¹ S for the fewer columns of Hᵀ = S G: S the unit vectors of the dofs the
        active rows touch (G = H among them, transposed, sparse; a contact's three rows share
        their nodes) or S = Hᵀ itself (G = I, None; when contacts on triangles touch more dofs
        than rows)."""
        H = rows.body_matrix(body, self.solver.fem.n_nodes)[:, self.free]
        self.active = np.flatnonzero(H.getnnz(axis=1))
        self.H = H = H[self.active].tocsr()
        touched = np.flatnonzero(H.getnnz(axis=0))
        if len(touched) < len(self.active):
            S = np.zeros((len(self.free), len(touched)))
            S[touched, np.arange(len(touched))] = 1.0
            self.G = H[:, touched].T.tocsr()
        else:
            S, self.G = H.T.toarray(), None
        self.B = self._inverse_between(S) if len(self.active) else np.zeros((0, 0))

    def _inverse_between(self, S: np.ndarray) -> np.ndarray:
        """Sᵀ A⁻¹ S: from CHOLMOD's factor as Yᵀ Y, Y = D^-½ L⁻¹ P S (a forward substitution; D = I
        for the supernodal LLᵀ); from the LU by a full solve. (The products avoid a threaded dense
        GEMM: at these sizes OpenBLAS's threads cost more than the product, many times so while
        other work shares the cores.)"""
        if self.factorization != "cholmod":
            return sp.csr_matrix(S.T) @ self._solve(S)
        factor = self._symbolic
        Y = factor.solve_L(factor.apply_P(S), use_LDLt_decomposition=self._ldlt)
        if self._ldlt:
            Y /= np.sqrt(factor.D())[:, None]
        upper = scipy.linalg.blas.dsyrk(1.0, Y, trans=1)
        return upper + np.triu(upper, 1).T

    def add_to(self, W: np.ndarray) -> None:
        """W (numpy, n_rows²) += h H A⁻¹ Hᵀ = h Gᵀ B G (B itself where G = I)."""
        if len(self.active):
            B = self.B if self.G is None else self.G.T @ (self.G.T @ self.B).T     # B symmetric
            W[np.ix_(self.active, self.active)] += self.solver.dt * B

    def correct(self, lam: np.ndarray) -> None:
        if not len(self.active):
            return
        s = self.solver
        dx = np.zeros(3 * s.fem.n_nodes)
        dx[self.free] = s.dt * self._solve(self.H.T @ lam[self.active])
        _displace(s.x, s.v, dx.reshape(-1, 3).astype(real_numpy()), s.dt)


@ti.kernel
def _displace(x: ti.types.ndarray(), v: ti.types.ndarray(), dx: ti.types.ndarray(), h: float):
    """x += dx, v += dx / h in the solver's arrays (the exact correction: one launch, where reading
    and writing both arrays through numpy took four)."""
    for k in range(dx.shape[0]):
        d = ti.Vector([dx[k, 0], dx[k, 1], dx[k, 2]])
        x[k] = x[k] + d
        v[k] = v[k] + d / h
