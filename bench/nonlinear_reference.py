"""Static equilibrium of a tetrahedral body under dead loads, in numpy/scipy: the references the
accuracy bench compares the simulator's model against.

Models (all on the same linear tetrahedra, same mesh, same lumped body force):
  "stvk"     St Venant–Kirchhoff, W = μ E:E + λ/2 (tr E)², E = ½(FᵀF − I): geometrically exact,
             the nonlinear reference (exact analytic tangent).
  "large", "polar"
             the co-rotational model of tissue.fem: fₑ = −Rₑ Kₑ (Rₑᵀ xₑ − Xₑ), Kₑ from
             tissue.solver.reference.element_stiffness, Rₑ from edge frames ("large", as
             reference.element_rotations, restated vectorised) or the polar decomposition of F
             ("polar", batched SVD); tests/test_stability.py checks both against reference.linearise.
             Its exact tangent (the rotations' derivative included, which the dynamic solver
             neglects) is differenced element by element: each element's force depends on its 12
             coordinates only, so 24 vectorised force evaluations give every element's 12×12
             Jacobian to ~1e-9 relative, and Newton converges quadratically.
  "invertible"
             "polar" plus the compression limit of tissue.fem.compression_limit: per element
             V Σᵢ ψ(σ̂ᵢ) over the signed singular values σ̂ of F (the smallest negated in an
             inverted element), ψ(σ̂) = κ c² φ(σ̂/c) below c, φ(s) = (s − 1)²/(2s) down to s₀ and
             its tangent line at s₀ below, κ = COMPRESSION_STIFFNESS (λ + 2μ),
             c = COMPRESSION_LIMIT, s₀ = BARRIER_END; its force is the analytic gradient
             U diag(ψ'(σ̂)) Vᵀ (batched SVD).
  "linear"   the rest-shape linear model, one sparse solve.

Equilibrium f_int(x) + f_ext = 0 on the free nodes by full Newton steps (sparse LU) along a load
ramp whose increment doubles after a converged increment and halves after a failed one (a line
search on ‖r‖ only slows it down here: the first step of an increment stretches the beam and
raises ‖r‖ on the way to the answer). Converged when ‖r‖ ≤ 1e-8 ‖f_ext‖ or the Newton update falls
under 1e-12 of the body's size (the round-off floor of ‖r‖ under small loads).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tissue.fem import Material
from tissue.mesh import TetMesh
from tissue.solver.reference import element_stiffness

MODELS = ("stvk", "large", "polar", "invertible", "linear")


@dataclass
class Body:
    """A mesh, its material and its clamped nodes, with the rest-shape data every model needs."""

    mesh: TetMesh
    material: Material
    fixed: np.ndarray
    grads: np.ndarray = field(init=False, repr=False)    # (m, 4, 3) ∇N of the rest shape
    Ke: np.ndarray = field(init=False, repr=False)       # (m, 12, 12)
    rows: np.ndarray = field(init=False, repr=False)     # COO pattern of the element blocks
    cols: np.ndarray = field(init=False, repr=False)
    free: np.ndarray = field(init=False, repr=False)     # free dofs
    rest_frames: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        X = self.mesh.points[self.mesh.tets]
        P = np.concatenate([np.ones((len(X), 4, 1)), X], axis=2)
        self.grads = np.linalg.inv(P)[:, 1:, :].transpose(0, 2, 1)
        self.Ke = element_stiffness(self.mesh, self.material)
        self.rest_frames = edge_frames(X)
        dofs = (3 * self.mesh.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
        self.rows = np.repeat(dofs, 12, axis=1).ravel()
        self.cols = np.tile(dofs, (1, 12)).ravel()
        mask = np.ones(self.mesh.n_points, dtype=bool)
        mask[np.asarray(self.fixed, dtype=np.int64)] = False
        self.free = np.flatnonzero(np.repeat(mask, 3))

    @property
    def lumped_mass(self) -> np.ndarray:
        m = np.zeros(self.mesh.n_points)
        np.add.at(m, self.mesh.tets.ravel(), np.repeat(self.material.density * self.mesh.volumes / 4, 4))
        return m

    def assemble_vector(self, fe: np.ndarray) -> np.ndarray:
        """(m, 4, 3) element nodal vectors -> (n, 3)."""
        out = np.zeros((self.mesh.n_points, 3))
        for a in range(4):
            np.add.at(out, self.mesh.tets[:, a], fe[:, a])
        return out

    def assemble_matrix(self, ke: np.ndarray) -> sp.csr_matrix:
        n = 3 * self.mesh.n_points
        return sp.csr_matrix((ke.ravel(), (self.rows, self.cols)), shape=(n, n))


# ---- element forces (m, 4, 3) and energies (m,) from element coordinates xe (m, 4, 3) -----------

def polar_rotations(F: np.ndarray) -> np.ndarray:
    """Rotation of F = R S for a stack of F, the closest proper one for inverted F (as the simulator)."""
    U, _, Vt = np.linalg.svd(F)
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, -1] *= -1
    return U @ Vt


def compression_limit(body: Body, xe: np.ndarray):
    """The "invertible" compression limit's element forces (m, 4, 3) and energies (m,)."""
    from tissue.fem.compression_limit import BARRIER_END, COMPRESSION_LIMIT, COMPRESSION_STIFFNESS

    lam, mu = body.material.lame
    kappa, c, s0 = COMPRESSION_STIFFNESS * (lam + 2 * mu), COMPRESSION_LIMIT, BARRIER_END
    U, s, Vt = np.linalg.svd(deformation_gradients(body, xe))
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, -1] *= -1
    s[flip, -1] *= -1
    r = s / c                                   # the barrier's φ(r) = r/2 − 1 + 1/(2r) ...
    barrier = r >= s0
    q = np.where(barrier, r, s0)
    phi = np.where(barrier, q / 2 - 1 + 1 / (2 * q),     # ... or its tangent line at s₀
                   s0 / 2 - 1 + 1 / (2 * s0) + (0.5 - 0.5 / s0 ** 2) * (r - s0))
    dphi = 0.5 - 0.5 / q ** 2
    active = r < 1.0
    V = body.mesh.volumes
    P = np.einsum("mij,mj,mjk->mik", U, np.where(active, kappa * c * dphi, 0.0), Vt)
    energy = V * kappa * c * c * np.where(active, phi, 0.0).sum(1)
    return -V[:, None, None] * np.einsum("mij,maj->mai", P, body.grads), energy


def edge_frames(xe: np.ndarray) -> np.ndarray:
    """Orthonormal frames (columns) of the triangles (x0, x1, x2): x along x0x1, z normal."""
    ex = xe[:, 1] - xe[:, 0]
    ex = ex / np.linalg.norm(ex, axis=1, keepdims=True)
    ez = np.cross(ex, xe[:, 2] - xe[:, 0])
    ez = ez / np.linalg.norm(ez, axis=1, keepdims=True)
    return np.stack([ex, np.cross(ez, ex), ez], axis=2)


def deformation_gradients(body: Body, xe: np.ndarray) -> np.ndarray:
    return np.einsum("mai,maj->mij", xe, body.grads)


def corotational_element(body: Body, xe: np.ndarray, rotation: str):
    """Co-rotational element forces −R Kₑ (Rᵀ xₑ − Xₑ) and energies ½ uₗᵀ Kₑ uₗ."""
    m = len(xe)
    if rotation == "invertible":
        forces, energies = corotational_element(body, xe, "polar")
        extra_forces, extra = compression_limit(body, xe)
        return forces + extra_forces, energies + extra
    if rotation == "polar":
        R = polar_rotations(deformation_gradients(body, xe))
    elif rotation == "large":
        R = edge_frames(xe) @ body.rest_frames.transpose(0, 2, 1)
    else:
        R = np.broadcast_to(np.eye(3), (m, 3, 3))
    Xe = body.mesh.points[body.mesh.tets]
    local = (np.einsum("mji,maj->mai", R, xe) - Xe).reshape(m, 12)
    stress = np.einsum("mij,mj->mi", body.Ke, local).reshape(m, 4, 3)
    forces = -np.einsum("mij,maj->mai", R, stress)
    return forces, 0.5 * np.einsum("mi,mi->m", local, stress.reshape(m, 12))


def stvk_element(body: Body, xe: np.ndarray, tangent: bool = False):
    """St Venant–Kirchhoff element forces, energies and (optionally) 12×12 tangents −∂f/∂x."""
    lam, mu = body.material.lame
    V = body.mesh.volumes
    F = deformation_gradients(body, xe)
    E = 0.5 * (np.einsum("mki,mkj->mij", F, F) - np.eye(3))
    trE = np.trace(E, axis1=1, axis2=2)
    S = 2 * mu * E + lam * trE[:, None, None] * np.eye(3)
    P = F @ S
    forces = -V[:, None, None] * np.einsum("mij,maj->mai", P, body.grads)
    energy = V * (mu * np.einsum("mij,mij->m", E, E) + 0.5 * lam * trE ** 2)
    if not tangent:
        return forces, energy
    # dP_ik/dF_jl = δ_ij S_lk + μ (F_il F_jk + (F Fᵀ)_ij δ_kl) + λ F_ik F_jl
    I = np.eye(3)
    FFt = F @ F.transpose(0, 2, 1)
    A = (np.einsum("ij,mlk->mikjl", I, S) + mu * np.einsum("mil,mjk->mikjl", F, F)
         + mu * np.einsum("mij,kl->mikjl", FFt, I) + lam * np.einsum("mik,mjl->mikjl", F, F))
    ke = V[:, None, None] * np.einsum("mak,mikjl,mbl->maibj", body.grads, A, body.grads,
                                      optimize=True).reshape(-1, 12, 12)
    return forces, energy, ke


def element_forces(body: Body, model: str, xe: np.ndarray):
    if model == "stvk":
        return stvk_element(body, xe)
    return corotational_element(body, xe, model)


def differenced_tangents(body: Body, model: str, xe: np.ndarray, step: float) -> np.ndarray:
    """(m, 12, 12) −∂fₑ/∂xₑ by central differences, all elements at once."""
    m = len(xe)
    ke = np.empty((m, 12, 12))
    for k in range(12):
        d = np.zeros((4, 3))
        d.flat[k] = step
        plus, _ = element_forces(body, model, xe + d)
        minus, _ = element_forces(body, model, xe - d)
        ke[:, :, k] = -(plus - minus).reshape(m, 12) / (2 * step)
    return ke


# ---- global quantities -----------------------------------------------------------------------

def internal_forces(body: Body, model: str, x: np.ndarray) -> np.ndarray:
    return body.assemble_vector(element_forces(body, model, x[body.mesh.tets])[0])


def strain_energy(body: Body, model: str, x: np.ndarray) -> float:
    if model == "linear":
        u = (x - body.mesh.points).ravel()
        return 0.5 * u @ (body.assemble_matrix(body.Ke) @ u)
    return float(element_forces(body, model, x[body.mesh.tets])[1].sum())


def tangent(body: Body, model: str, x: np.ndarray) -> sp.csr_matrix:
    """−∂f_int/∂x, assembled."""
    xe = x[body.mesh.tets]
    if model == "stvk":
        ke = stvk_element(body, xe, tangent=True)[2]
    elif model == "linear":
        ke = body.Ke
    else:
        size = np.cbrt(body.mesh.volumes.mean())
        ke = differenced_tangents(body, model, xe, 1e-6 * size)
    return body.assemble_matrix(ke)


@dataclass
class StaticResult:
    x: np.ndarray
    newton_iterations: int
    residual: float          # ‖r_free‖ / ‖f_ext‖ at the end
    loads: list              # the load factors reached


def solve_static(body: Body, model: str, external: np.ndarray, x0: np.ndarray | None = None,
                 start: float = 0.0, increments: int = 4, tol: float = 1e-8, max_newton: int = 20,
                 min_increment: float = 1e-4) -> StaticResult:
    """Equilibrium under `external` (n, 3) nodal forces, ramped from load factor `start` (the state
    x0 being in equilibrium at it) to 1."""
    free = body.free
    x = (body.mesh.points if x0 is None else x0).copy()
    fext = external.ravel()
    scale = np.linalg.norm(fext[free])
    size = np.ptp(body.mesh.points, axis=0).max()
    if model == "linear":
        K = body.assemble_matrix(body.Ke).tocsc()[free][:, free]
        u = np.zeros(x.size)
        u[free] = spla.spsolve(K, fext[free])
        return StaticResult(body.mesh.points + u.reshape(-1, 3), 1, 0.0, [1.0])

    def residual(x, load):
        return (internal_forces(body, model, x).ravel() + load * fext)[free]

    total, load, step = 0, start, (1.0 - start) / increments
    loads = []
    while load < 1.0 - 1e-12:
        target = min(1.0, load + step)
        y, r = x.copy(), residual(x, target)
        norm = np.linalg.norm(r)
        converged = False
        for _ in range(max_newton + 1):
            if norm <= tol * scale:
                converged = True
                break
            K = tangent(body, model, y).tocsc()[free][:, free]
            d = np.zeros(y.size)
            d[free] = spla.spsolve(K, r)
            y = y + d.reshape(-1, 3)
            r = residual(y, target)
            if not np.isfinite(r).all() or np.linalg.norm(r) > 1e8 * scale:
                break
            total += 1
            norm = np.linalg.norm(r)
            if np.abs(d).max() <= 1e-12 * size:   # at the round-off floor of ‖r‖ (small loads)
                norm = 0.0
        if converged:
            x, load = y, target
            loads.append(load)
            step = min(2 * step, 1.0 - load)
        else:
            step *= 0.5
            if step < min_increment:
                raise RuntimeError(f"{model}: Newton stalled at load factor {load:.4g} "
                                   f"(‖r‖/‖f‖ = {norm / scale:.2e})")
    r = residual(x, 1.0)
    return StaticResult(x, total, float(np.linalg.norm(r) / scale), loads)


# ---- loads on a cantilever beam along +x (tissue.mesh.beam), clamped at x = 0 -----------------

def clamped_nodes(mesh: TetMesh) -> np.ndarray:
    return np.flatnonzero(mesh.points[:, 0] <= mesh.points[:, 0].min() + 1e-9)


def tip_nodes(mesh: TetMesh) -> np.ndarray:
    return np.flatnonzero(mesh.points[:, 0] >= mesh.points[:, 0].max() - 1e-9)


def tip_load(mesh: TetMesh, force=(0.0, 0.0, -1.0)) -> np.ndarray:
    """A total force spread over the tip face's nodes in proportion to their share of its area
    (uniform grid: corners 1/4, edges 1/2, interior 1 of a cell's area)."""
    tip = tip_nodes(mesh)
    yz = mesh.points[tip][:, 1:]
    weight = np.ones(len(tip))
    for axis in range(2):
        on_edge = np.isclose(yz[:, axis], yz[:, axis].min()) | np.isclose(yz[:, axis], yz[:, axis].max())
        weight[on_edge] *= 0.5
    f = np.zeros((mesh.n_points, 3))
    f[tip] = np.outer(weight / weight.sum(), force)
    return f


def body_load(body: Body, acceleration=(0.0, 0.0, -1.0)) -> np.ndarray:
    """Lumped body force m_i a (the simulator's gravity)."""
    return np.outer(body.lumped_mass, acceleration)


def tip_deflection(mesh: TetMesh, x: np.ndarray) -> tuple[float, float]:
    """Mean (−z, x) displacement of the tip face's nodes: the deflection and the shortening."""
    tip = tip_nodes(mesh)
    u = (x[tip] - mesh.points[tip]).mean(axis=0)
    return float(-u[2]), float(-u[0])
