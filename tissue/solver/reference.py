"""The assembled reference: the same implicit Euler step, built as a scipy sparse matrix from the
textbook element stiffness Kₑ = V Bᵀ D B and solved directly.

It shares no code with the Taichi kernels (rotations, stiffness and forces are recomputed here
in numpy from their definitions), so the tests and the error reports compare against something
the simulator did not produce. It also gives the rest-shape matrix A₀ whose inverse is the
compliance of the contact layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg.lapack
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import TissueError
from ..fem.material import Material
from ..mesh import TetMesh


def element_stiffness(mesh: TetMesh, material: Material) -> np.ndarray:
    """(m, 12, 12) element stiffness V Bᵀ D B of linear tetrahedra, in Voigt notation."""
    lam, mu = material.lame
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[:3, :3] += 2 * mu * np.eye(3)
    D[3:, 3:] = mu * np.eye(3)
    X = mesh.points[mesh.tets]                                   # (m, 4, 3)
    # Shape-function gradients from the inverse of [[1, X]] (4×4).
    P = np.concatenate([np.ones((len(X), 4, 1)), X], axis=2)
    grads = np.linalg.inv(P)[:, 1:, :].transpose(0, 2, 1)        # (m, 4 nodes, 3)
    B = np.zeros((len(X), 6, 12))
    for a in range(4):
        gx, gy, gz = grads[:, a, 0], grads[:, a, 1], grads[:, a, 2]
        c = 3 * a
        B[:, 0, c], B[:, 1, c + 1], B[:, 2, c + 2] = gx, gy, gz
        B[:, 3, c], B[:, 3, c + 1] = gy, gx          # γ_xy
        B[:, 4, c + 1], B[:, 4, c + 2] = gz, gy      # γ_yz
        B[:, 5, c], B[:, 5, c + 2] = gz, gx          # γ_xz
    return mesh.volumes[:, None, None] * np.einsum("eki,kl,elj->eij", B, D, B)


def _frames(p: np.ndarray) -> np.ndarray:
    ex = p[:, 1] - p[:, 0]
    ex /= np.linalg.norm(ex, axis=1, keepdims=True)
    ez = np.cross(ex, p[:, 2] - p[:, 0])
    ez /= np.linalg.norm(ez, axis=1, keepdims=True)
    return np.stack([ex, np.cross(ez, ex), ez], axis=2)


def element_rotations(mesh: TetMesh, x: np.ndarray, method: str) -> np.ndarray:
    """(m, 3, 3) rotations: "large" (edge frames), "polar" (of F), "linear" (identity)."""
    m = mesh.n_tets
    if method == "linear":
        return np.tile(np.eye(3), (m, 1, 1))
    if method == "large":
        return np.einsum("eij,ekj->eik", _frames(x[mesh.tets]), _frames(mesh.points[mesh.tets]))
    X, t = mesh.points, mesh.tets
    Dm = np.stack([X[t[:, i]] - X[t[:, 0]] for i in (1, 2, 3)], axis=2)
    Ds = np.stack([x[t[:, i]] - x[t[:, 0]] for i in (1, 2, 3)], axis=2)
    F = Ds @ np.linalg.inv(Dm)
    R = np.empty_like(F)
    for e in range(m):
        U, s, Vt = np.linalg.svd(F[e])
        if np.linalg.det(U @ Vt) < 0:   # inverted: reflect the smallest singular direction
            U[:, -1] *= -1
        R[e] = U @ Vt
    return R


def _block_diagonal_rotation(R: np.ndarray) -> sp.csr_matrix:
    m = len(R)
    rows = np.repeat(np.arange(12 * m).reshape(m, 4, 3), 3, axis=2).reshape(m, -1)
    cols = np.tile(np.arange(12 * m).reshape(m, 4, 1, 3), (1, 1, 3, 1)).reshape(m, -1)
    vals = np.tile(R[:, None], (1, 4, 1, 1)).reshape(m, -1)
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(12 * m, 12 * m))


def _block_diagonal(blocks: np.ndarray) -> sp.csr_matrix:
    """The (12m × 12m) block diagonal of m 12×12 blocks, zeros kept, as scipy's block_diag makes it
    (the same arrays, without its per-block conversions)."""
    m = len(blocks)
    indices = np.tile(np.arange(12 * m).reshape(m, 1, 12), (1, 12, 1)).reshape(-1)
    return sp.csr_matrix((blocks.reshape(-1), indices, np.arange(0, 144 * m + 1, 12)), shape=(12 * m, 12 * m))


def _scatter_matrix(mesh: TetMesh) -> sp.csr_matrix:
    """G: (3n × 12m), element-local dofs -> global dofs."""
    m = mesh.n_tets
    dofs = (3 * mesh.tets[:, :, None] + np.arange(3)).reshape(-1)
    return sp.csr_matrix((np.ones(12 * m), (dofs, np.arange(12 * m))), shape=(3 * mesh.n_points, 12 * m))


@dataclass
class LinearisedStep:
    """The step's linear system A dv = b (all dofs) and the pieces it is made of."""

    A: sp.csr_matrix
    b: np.ndarray
    stiffness: sp.csr_matrix       # Σ R Kₑ Rᵀ (positive semi-definite)
    forces: np.ndarray             # elastic forces (3n,)
    mass: np.ndarray               # lumped (3n,)


def linearise(mesh: TetMesh, material: Material, x: np.ndarray, v: np.ndarray, dt: float,
              gravity=(0.0, 0.0, -9.81), rayleigh_mass=0.0, rayleigh_stiffness=0.0,
              rotation: str = "large", external=None) -> LinearisedStep:
    Ke = _block_diagonal(element_stiffness(mesh, material))
    R = _block_diagonal_rotation(element_rotations(mesh, x, rotation))
    G = _scatter_matrix(mesh)
    K = (G @ R @ Ke @ R.T @ G.T).tocsr()
    local_x = G.T @ x.reshape(-1)
    local_X = G.T @ mesh.points.reshape(-1)
    forces = -(G @ (R @ (Ke @ (R.T @ local_x - local_X))))
    mass = np.zeros(mesh.n_points)
    np.add.at(mass, mesh.tets.reshape(-1), np.repeat(material.density * mesh.volumes / 4.0, 4))
    mass3 = np.repeat(mass, 3)
    h = dt
    f = forces + mass3 * np.tile(gravity, mesh.n_points) - rayleigh_mass * mass3 * v.reshape(-1) \
        - rayleigh_stiffness * (K @ v.reshape(-1))
    if external is not None:
        f = f + np.asarray(external, dtype=np.float64).reshape(-1)
    A = (sp.diags((1 + h * rayleigh_mass) * mass3) + (h * rayleigh_stiffness + h * h) * K).tocsr()
    b = h * f - h * h * (K @ v.reshape(-1))
    return LinearisedStep(A=A, b=b, stiffness=K, forces=forces, mass=mass3)


def free_dofs(n_points: int, fixed) -> np.ndarray:
    mask = np.ones(n_points, dtype=bool)
    mask[np.asarray(fixed, dtype=np.int64)] = False
    return np.flatnonzero(np.repeat(mask, 3))


def reference_step(mesh: TetMesh, material: Material, x: np.ndarray, v: np.ndarray, dt: float,
                   fixed=(), **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """One implicit Euler step solved directly (sparse LU); returns the new (x, v)."""
    system = linearise(mesh, material, x, v, dt, **kwargs)
    free = free_dofs(mesh.n_points, fixed)
    dv = np.zeros(3 * mesh.n_points)
    dv[free] = spla.spsolve(system.A[free][:, free].tocsc(), system.b[free])
    v_new = v.reshape(-1) + dv
    v_new[np.setdiff1d(np.arange(3 * mesh.n_points), free)] = 0.0
    v_new = v_new.reshape(-1, 3)
    return x + dt * v_new, v_new


def rest_matrix(mesh: TetMesh, material: Material, dt: float, rayleigh_mass=0.0,
                rayleigh_stiffness=0.0) -> sp.csr_matrix:
    """The step matrix A₀ of the rest configuration (all dofs, no fixed ones removed)."""
    return linearise(mesh, material, mesh.points, np.zeros_like(mesh.points), dt,
                     rayleigh_mass=rayleigh_mass, rayleigh_stiffness=rayleigh_stiffness).A


def rest_compliance(mesh: TetMesh, material: Material, dt: float, fixed=(),
                    rayleigh_mass=0.0, rayleigh_stiffness=0.0, matrix=None) -> np.ndarray:
    """Dense A₀⁻¹ of the rest configuration (zero rows/columns at fixed dofs); `matrix`: A₀
    (rest_matrix's) where the caller has it.

    A₀ = (1 + h α_M) M + (h α_K + h²) K is symmetric positive definite on the free dofs (a positive
    lumped mass plus a positive semi-definite stiffness), so it is inverted through its Cholesky
    factor (LAPACK potrf, potri): half the flops of LU's inverse, and exactly symmetric."""
    A = rest_matrix(mesh, material, dt, rayleigh_mass, rayleigh_stiffness) if matrix is None else matrix
    free = free_dofs(mesh.n_points, fixed)
    A_free = A[free][:, free].toarray()
    potrf, potri = scipy.linalg.lapack.get_lapack_funcs(("potrf", "potri"), (A_free,))
    factor, info = potrf(A_free, lower=True, overwrite_a=True)
    if info == 0:
        inverse, info = potri(factor, lower=True, overwrite_c=True)
    if info != 0:
        node = free[abs(info) - 1] // 3
        raise TissueError(f"{mesh.source}: rest compliance: the rest matrix is not positive definite "
                          f"(LAPACK info {info}, at node {node}: a node of no element, or a material without "
                          f"mass or stiffness there)")
    upper = np.triu_indices(len(free), 1)
    inverse[upper] = inverse[upper[::-1]]          # potri fills the lower triangle only
    C = np.zeros((3 * mesh.n_points, 3 * mesh.n_points))
    C[np.ix_(free, free)] = inverse
    return C
