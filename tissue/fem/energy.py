"""The elastic energy of a body's co-rotational elements at given positions: numpy on the host
(the reference), and `element_energy`, the same per element in a Taichi function (the energy
check's kernel, tissue.solver.step_control, computes it on the device): `rotated_energy` from F's
polar rotation where Newton–Schulz finds it, else `polar_energy` from the signed principal
stretches.

For "polar" the linear co-rotational energy is a true potential of its forces: with R the polar
rotation of F and ε = RᵀF − I (symmetric), an element stores V (μ ε:ε + λ/2 (tr ε)²), which is
½ uᵀ Kₑ u for the local displacement u = Rᵀx − X. "invertible" adds its compression limit
V Σ ψ(σ̂ᵢ) over the signed principal stretches, ψ the barrier of tissue.fem.compression_limit. "large"
(edge frames) has no energy of its own, its forces are not a gradient: the polar energy is the
one it approximates, and the one used for it here. "linear" is ε = sym(F) − I.
"""

import numpy as np
import taichi as ti

from .compression_limit import BARRIER_END, COMPRESSION_LIMIT, COMPRESSION_STIFFNESS, compressed, limit_energy
from .corotational import FLAT_DETERMINANT, deformation_gradient
from .model import BodyModel
from .rotations import newton_schulz, symmetric_eigen


def deformation_gradients(model: BodyModel, x: np.ndarray) -> np.ndarray:
    """(elements, 3, 3) F = Ds Dm⁻¹, Ds the current edge matrix (columns xᵢ − x₀)."""
    tets = model.tets
    Ds = np.stack([x[tets[:, i]] - x[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    return Ds @ model.Dm_inv


def element_energies(model: BodyModel, x: np.ndarray, rotation: str) -> np.ndarray:
    """(elements,) elastic energy of each element (J)."""
    F = deformation_gradients(model, np.asarray(x, dtype=np.float64))
    volume, lam, mu = model.elastic.T
    if rotation == "linear":
        eps = 0.5 * (F + F.transpose(0, 2, 1)) - np.eye(3)
        return volume * (mu * (eps * eps).sum((1, 2)) + 0.5 * lam * np.trace(eps, axis1=1, axis2=2) ** 2)
    # Signed SVD: F = U Σ̂ Vᵀ with U, V rotations (σ̂ smallest < 0 in an inverted element: det F <
    # 0), R = U Vᵀ and RᵀF = V Σ̂ Vᵀ: ε has the eigenvalues σ̂ᵢ − 1. The energy needs no vectors:
    # σᵢ² are the eigenvalues of FᵀF (a symmetric eigensolve, a third of an SVD's time; the
    # energy check reads this twice a step), exact to ε‖F‖²/σ, far below any use unless an
    # element is collapsed to σ ~ 1e-8.
    s = np.sqrt(np.maximum(np.linalg.eigvalsh(F.transpose(0, 2, 1) @ F), 0.0))      # ascending
    s[:, 0] *= np.where(np.linalg.det(F) < 0, -1.0, 1.0)
    e = s - 1.0
    energy = volume * (mu * (e * e).sum(1) + 0.5 * lam * e.sum(1) ** 2)
    if rotation == "invertible":
        energy = energy + volume * limit_energies(COMPRESSION_STIFFNESS * (lam + 2 * mu), s)
    return energy


def limit_energies(kappa: np.ndarray, stretches: np.ndarray) -> np.ndarray:
    """(elements,) Σᵢ ψ(σ̂ᵢ) of the compression limit (per unit volume), κ per element:
    κ c² φ(σ̂/c) with φ(s) = (s − 1)²/(2s) below c, continued by its tangent line below BARRIER_END."""
    c = COMPRESSION_LIMIT
    s = stretches / c
    t = np.maximum(s, BARRIER_END)
    h = s - t
    phi = (t - 1.0) ** 2 / (2.0 * t) + 0.5 * (1.0 - 1.0 / t ** 2) * h
    return kappa * c * c * np.where(s < 1.0, phi, 0.0).sum(1)


def elastic_energy(model: BodyModel, x: np.ndarray, rotation: str) -> float:
    return float(element_energies(model, x, rotation).sum())


@ti.func
def element_energy(m: ti.template(), e, x: ti.template(), rotation: ti.template(), tol):
    """Element e's elastic energy (J) at positions x, as `element_energies`: from F's polar
    rotation where Newton–Schulz finds it (to `tol`; F nearly orthogonal and not inverted: a
    tissue's elements under moderate strain), with fewer dependent operations than the
    eigensolve of FᵀF and the same energy to round-off; elsewhere from the stretches."""
    F = deformation_gradient(m, e, x)
    energy = 0.0
    if ti.static(rotation == "linear"):
        volume, lam, mu = m.elastic[e][0], m.elastic[e][1], m.elastic[e][2]
        eps = 0.5 * (F + F.transpose()) - ti.Matrix.identity(float, 3)
        energy = volume * (mu * eps.norm_sqr() + 0.5 * lam * eps.trace() ** 2)
    else:
        R, near = newton_schulz(F, tol)
        if near and F.determinant() > 0.0:
            energy = rotated_energy(m, e, R, F, rotation)
        else:
            energy = polar_energy(m, e, F, rotation)
    return energy


@ti.func
def element_energy_at_rotations(m: ti.template(), w: ti.template(), e, x: ti.template(), rotation: ti.template(),
                                tol):
    """`element_energy`, from the rotations w.R of the FEM's last update where they are F's polar
    rotations ("polar", "invertible", elements not flat: tissue.fem.corotational.element_rotation):
    a step's start, whose rotations the step computes anyway."""
    energy = 0.0
    if ti.static(rotation == "polar" or rotation == "invertible"):
        F = deformation_gradient(m, e, x)
        if ti.abs(F.determinant()) > FLAT_DETERMINANT:
            energy = rotated_energy(m, e, w.R[e], F, rotation)
        else:
            energy = polar_energy(m, e, F, rotation)
    else:
        energy = element_energy(m, e, x, rotation, tol)
    return energy


@ti.func
def polar_energy(m: ti.template(), e, F, rotation: ti.template()):
    """Element e's co-rotational energy at F, its rotation the polar one: σᵢ² by Jacobi rotations on
    FᵀF (tissue.fem.rotations.symmetric_eigen), the smallest σ negative where det F < 0."""
    volume, lam, mu = m.elastic[e][0], m.elastic[e][1], m.elastic[e][2]
    squares, _ = symmetric_eigen(F.transpose() @ F)
    s = ti.sqrt(ti.max(squares, 0.0))
    if F.determinant() < 0.0:           # the smallest stretch turns negative (static indices only)
        smallest, flipped = ti.min(s[0], s[1], s[2]), False
        for i in ti.static(range(3)):
            if not flipped and s[i] == smallest:
                s[i], flipped = -s[i], True
    strain = s - 1.0
    energy = volume * (mu * strain.norm_sqr() + 0.5 * lam * strain.sum() ** 2)
    if ti.static(rotation == "invertible"):
        kappa = COMPRESSION_STIFFNESS * (lam + 2.0 * mu)
        for i in ti.static(range(3)):
            energy += volume * limit_energy(kappa, s[i])
    return energy


@ti.func
def rotated_energy(m: ti.template(), e, R, F, rotation: ti.template()):
    """`polar_energy` given F's polar rotation R: ε = RᵀF − I is symmetric, its eigenvalues σ̂ᵢ − 1,
    so the energy needs no eigensolve, unless the compression limit ("invertible") is active."""
    volume, lam, mu = m.elastic[e][0], m.elastic[e][1], m.elastic[e][2]
    G = R.transpose() @ F
    S = 0.5 * (G + G.transpose())
    strain = S - ti.Matrix.identity(float, 3)
    energy = volume * (mu * strain.norm_sqr() + 0.5 * lam * strain.trace() ** 2)
    if ti.static(rotation == "invertible"):
        if compressed(S):
            stretches, _ = symmetric_eigen(S)
            kappa = COMPRESSION_STIFFNESS * (lam + 2.0 * mu)
            for i in ti.static(range(3)):
                energy += volume * limit_energy(kappa, stretches[i])
    return energy
