"""Co-rotational linear tetrahedra (tissue.fem) against references the kernels did not produce:
rigid motions built with scipy's Rotation, the patch test's closed-form stress λ tr(ε) I + 2μ ε,
and the textbook Kₑ = V Bᵀ D B assembled in scipy (tissue.solver.reference).

All element-level tests share one mesh (a box with jittered interior nodes, so that nothing
cancels by the symmetry of the regular grid) and one CorotationalFEM per (rotation, accumulation):
Taichi compiles kernels per object, and compiling is what costs here.
"""

import numpy as np
import pytest
import taichi as ti
from scipy.spatial.transform import Rotation

from tissue.errors import TissueError
from tissue.fem import CorotationalFEM, Material
from tissue.fem.rotations import ROTATION_TOLERANCE, polar_rotation, symmetric_eigen
from tissue.mesh import TetMesh, box
from tissue.solver import reference as ref

E, NU, RHO = 1.0e4, 0.3, 1000.0
SIZE = np.array([1.0, 0.8, 0.6])
L = 1.0                      # body size: forces are measured against E·L² (a stress times an area)
FORCE_SCALE = E * L ** 2
MATERIAL = Material(E, NU, RHO)


def jittered_box():
    """A 3×3×3-cell box whose 8 interior nodes are moved randomly by up to 25% of a cell: on the
    regular grid every interior node sees each Kuhn tetrahedron in each corner, which would make
    the patch test pass for any per-element-type stress."""
    mesh = box(size=tuple(SIZE), cells=(3, 3, 3))
    X = mesh.points.copy()
    interior = np.flatnonzero(np.all((X > 1e-9) & (X < SIZE - 1e-9), axis=1))
    rng = np.random.default_rng(7)
    X[interior] += rng.uniform(-0.25, 0.25, (len(interior), 3)) * SIZE / 3
    return TetMesh(X, mesh.tets, source="jittered box"), interior


MESH, INTERIOR = jittered_box()


@pytest.fixture(scope="module")
def fem(backend):
    """fem(rotation, accumulation="gather"): one CorotationalFEM per pair, built once."""
    cache = {}

    def get(rotation, accumulation="gather"):
        key = (rotation, accumulation)
        if key not in cache:
            cache[key] = CorotationalFEM(MESH, MATERIAL, rotation=rotation, accumulation=accumulation)
        return cache[key]

    return get


def random_rotation(seed, angle):
    axis = np.random.default_rng(seed).standard_normal(3)
    return Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()


def deformed_state(seed, amplitude=0.05):
    """A large rigid rotation (2.4 rad) of a randomly perturbed shape, moved away."""
    rng = np.random.default_rng(seed)
    Q = random_rotation(seed, 2.4)
    X = MESH.points
    return (X + amplitude * L * rng.standard_normal(X.shape)) @ Q.T + rng.standard_normal(3)


def lin_elastic_stress(G):
    lam, mu = MATERIAL.lame
    eps = 0.5 * (G + G.T)
    return lam * np.trace(eps) * np.eye(3) + 2 * mu * eps


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


# --- 1. rigid motions ---------------------------------------------------------------------------

@pytest.mark.parametrize("rotation", ["large", "polar"])
def test_rigid_motion_gives_zero_force_and_the_applied_rotation(fem, rotation):
    """Reference: a rigid motion x = Q X + t (Q from scipy, 2.5 rad about a random axis) stores no
    energy, so f = 0 and every element rotation is Q. Tolerance: |f| ≤ 1e-10 E·L² (E·L² is the
    force of a unit strain on the body's cross-section; round-off gives ~1e-15 of it) and
    |Rₑ - Q| ≤ 1e-12. Control: "linear" at the same state gives forces of order 0.1 E·L²."""
    Q = random_rotation(1, 2.5)
    X = MESH.points
    x = (X - X.mean(0)) @ Q.T + X.mean(0) + np.array([0.3, -2.0, 5.0])
    f = fem(rotation).elastic_forces_numpy(x)
    assert np.abs(f).max() <= 1e-10 * FORCE_SCALE
    R = fem(rotation).rotations_numpy(x)
    assert np.abs(R - Q).max() <= 1e-12
    # A pure translation too.
    assert np.abs(fem(rotation).elastic_forces_numpy(X + [4.0, -1.0, 2.5])).max() <= 1e-10 * FORCE_SCALE
    # Control: the small-displacement model is not rotation-invariant.
    assert np.abs(fem("linear").elastic_forces_numpy(x)).max() > 1e-2 * FORCE_SCALE


# --- 2. patch test ------------------------------------------------------------------------------

@pytest.mark.parametrize("rotation,scale", [("polar", 1e-2), ("polar", 0.2), ("linear", 1e-2), ("linear", 0.2)])
def test_patch_test_affine_displacement_is_in_equilibrium(fem, rotation, scale):
    """Reference: an affine displacement x = X + G X has a uniform stress, whose divergence is
    zero, so interior nodes carry no force (the patch test; G random, not symmetric). Exact for
    "polar" (one rotation for all elements: the polar factor of I + G) and "linear", so any G.
    Tolerance: |f_interior| ≤ 1e-12 of the force scale E·|G|·L² (round-off ~1e-14 of it at
    |G| = 1e-2: the strain RᵀF - I is formed by a cancellation of size 1/|G|)."""
    G = np.random.default_rng(3).standard_normal((3, 3))
    G *= scale / np.abs(G).max()
    X = MESH.points
    f = fem(rotation).elastic_forces_numpy(X + X @ G.T)
    assert np.abs(f[INTERIOR]).max() <= 1e-12 * FORCE_SCALE * scale
    assert np.abs(f).max() > 1e-3 * FORCE_SCALE * scale      # the boundary does feel the load


def test_patch_test_large_is_second_order(fem):
    """"large" (edge-frame rotations) takes each element's rotation from its own first three
    nodes, so on an irregular mesh the rotations of an affine state differ between elements by
    O(|G|); the stresses then differ by O(|G|²) and the patch test holds to second order only.
    Reference: the interior force relative to the force scale E·|G|·L² is below |G| (measured:
    ~0.026 |G| at |G| = 1e-3) and dividing G by 10 divides the absolute force by 100 ± 5%."""
    G = np.random.default_rng(3).standard_normal((3, 3))
    G *= 1e-3 / np.abs(G).max()
    X = MESH.points
    f1 = np.abs(fem("large").elastic_forces_numpy(X + X @ G.T)[INTERIOR]).max()
    f2 = np.abs(fem("large").elastic_forces_numpy(X + X @ (G / 10).T)[INTERIOR]).max()
    assert f1 <= 1e-3 * FORCE_SCALE * 1e-3
    assert f1 / f2 == pytest.approx(100.0, rel=0.05)


def test_patch_test_stress_polar_symmetric_gradient(fem):
    """Reference: for a symmetric positive definite G, F = I + G is its own stretch (R = I), so
    every element's stress is λ tr(G) I + 2μ G exactly. Tolerance 1e-12 relative to |σ|
    (round-off of the Newton polar iteration and of the 3×3 products, ~1e-15)."""
    A = np.random.default_rng(4).standard_normal((3, 3))
    G = 0.05 * (A @ A.T + 0.1 * np.eye(3))
    X = MESH.points
    sigma = fem("polar").element_stress_numpy(X + X @ G.T)
    expected = lin_elastic_stress(G)
    assert np.abs(sigma - expected).max() <= 1e-12 * np.abs(expected).max()
    np.testing.assert_allclose(fem("polar").rotations_numpy(X + X @ G.T), np.tile(np.eye(3), (MESH.n_tets, 1, 1)),
                               rtol=0, atol=1e-13)


def test_patch_test_stress_linear_any_gradient(fem):
    """Reference: the small-strain model's stress for x = X + G X is λ tr(ε) I + 2μ ε with
    ε = sym(G), for any G (here a random non-symmetric G of size 0.3). Tolerance 1e-12 relative."""
    G = np.random.default_rng(5).standard_normal((3, 3))
    G *= 0.3 / np.abs(G).max()
    X = MESH.points
    sigma = fem("linear").element_stress_numpy(X + X @ G.T)
    expected = lin_elastic_stress(G)
    assert np.abs(sigma - expected).max() <= 1e-12 * np.abs(expected).max()


# --- 3. against the assembled scipy reference ---------------------------------------------------

@pytest.mark.parametrize("rotation", ["large", "polar", "linear"])
@pytest.mark.parametrize("seed", [11, 12])
def test_forces_and_stiffness_product_match_assembled_reference(fem, rotation, seed):
    """Reference: tissue.solver.reference assembles Σ Gₑ Rₑ Kₑ Rₑᵀ Gₑᵀ in scipy from the textbook
    Kₑ = V Bᵀ D B (Voigt) and its own rotations (numpy edge frames / SVD polar). At a random
    deformed state (large rotation plus 5% random strain): the rotations agree to 1e-12, the
    elastic forces -Σ R Kₑ (Rᵀx - X) and the products -Σ R Kₑ Rᵀ p (random p) agree to 1e-12
    relative to their norms (both are sums of ~10² terms of round-off 1e-16)."""
    x = deformed_state(seed)
    model = fem(rotation)
    R = model.rotations_numpy(x)
    np.testing.assert_allclose(R, ref.element_rotations(MESH, x, rotation), rtol=0, atol=1e-12)
    system = ref.linearise(MESH, MATERIAL, x, np.zeros_like(x), dt=0.01, rotation=rotation)
    f = model.elastic_forces_numpy(x)
    assert rel(f.reshape(-1), system.forces) <= 1e-12
    p = np.random.default_rng(seed + 100).standard_normal(x.shape)
    Kp = model.stiffness_product_numpy(p)
    assert rel(Kp.reshape(-1), -(system.stiffness @ p.reshape(-1))) <= 1e-12


# --- 8. accumulation methods ------------------------------------------------------------------

@pytest.mark.parametrize("accumulation", ["atomic", "colouring"])
def test_accumulations_agree(fem, accumulation):
    """Reference: the gather accumulation (a different code path: per-element buffer summed
    per vertex). Forces and stiffness products at a random deformed state agree to 1e-12
    relative: only the order of the ~6 additions per node differs."""
    x = deformed_state(21)
    p = np.random.default_rng(22).standard_normal(x.shape)
    results = []
    for acc in ("gather", accumulation):
        model = fem("large", acc)
        results.append((model.elastic_forces_numpy(x), model.stiffness_product_numpy(p)))
    (fg, kg), (fa, ka) = results
    assert rel(fa, fg) <= 1e-12
    assert rel(ka, kg) <= 1e-12


def test_gather_is_bit_identical_across_objects(backend):
    """Reference: a second, freshly built CorotationalFEM with gather accumulation (fixed
    summation order) must give the very same bits: np.array_equal, no tolerance."""
    x = deformed_state(31)
    p = np.random.default_rng(32).standard_normal(x.shape)
    runs = []
    for _ in range(2):
        model = CorotationalFEM(MESH, MATERIAL, rotation="large", accumulation="gather")
        runs.append((model.elastic_forces_numpy(x), model.stiffness_product_numpy(p)))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert np.array_equal(runs[0][1], runs[1][1])


# --- 10. bad inputs -----------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs,name", [
    (dict(young=0.0), "young"), (dict(young=-5.0), "young"),
    (dict(poisson=0.5), "poisson"), (dict(poisson=0.7), "poisson"),
    (dict(poisson=-1.0), "poisson"), (dict(poisson=-1.5), "poisson"),
    (dict(density=0.0), "density"), (dict(density=-1.0), "density"),
    (dict(young=float("nan")), "young"),
])
def test_material_rejects_bad_values(kwargs, name):
    """Each invalid material parameter raises TissueError naming that parameter."""
    with pytest.raises(TissueError, match=name):
        Material(**kwargs)


def test_fem_rejects_unknown_rotation(backend):
    with pytest.raises(TissueError, match="rotation"):
        CorotationalFEM(MESH, MATERIAL, rotation="qr")


def test_fem_rejects_unknown_accumulation(backend):
    with pytest.raises(TissueError, match="accumulation"):
        CorotationalFEM(MESH, MATERIAL, accumulation="scatter")


def test_polar_rotation_of_inverted_elements_is_the_closest_proper_rotation(backend):
    """Every element mirrored (z -> -z after a random distortion): "polar" must return a proper
    rotation (det +1), the one of the SVD with the smallest singular direction flipped (Irving et
    al. 2004; scipy SVD in reference.element_rotations). The kernel finds that direction by Jacobi
    rotations (symmetric_eigen); where two singular values of one element nearly coincide the
    rotation is less well conditioned: 1e-6 leaves room for that."""
    mesh = box(size=(1, 1, 1), cells=(2, 2, 2))
    fem = CorotationalFEM(mesh, Material(), rotation="polar")
    x = mesh.points + 0.3 * np.random.default_rng(3).standard_normal(mesh.points.shape)
    x[:, 2] *= -1
    R = fem.rotations_numpy(x)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert np.abs(R - ref.element_rotations(mesh, x, "polar")).max() <= 1e-6


@ti.kernel
def _polar_kernel(a: ti.types.ndarray(), out: ti.types.ndarray()):
    for i in range(a.shape[0]):
        out[i] = polar_rotation(a[i], ROTATION_TOLERANCE["f64"])


def test_polar_rotation_matches_scipys_polar_near_and_far_from_orthogonal(backend):
    """F = Q S with S symmetric positive, its distance from I from 1e-8 to 0.5 (Newton–Schulz's
    region: ‖FᵀF − I‖ ≤ 0.5 for most) and beyond it (the scaled Newton iteration, also after
    Newton–Schulz gave up), against scipy.linalg.polar's (SVD) factor to 1e-13."""
    import scipy.linalg

    rng = np.random.default_rng(21)
    amplitudes = np.repeat([1e-8, 1e-3, 0.05, 0.2, 0.4, 1.0], 40)
    Q = Rotation.random(len(amplitudes), random_state=22).as_matrix()
    S = rng.standard_normal((len(amplitudes), 3, 3)) * amplitudes[:, None, None]
    S = 0.5 * (S + S.transpose(0, 2, 1))
    values, vectors = np.linalg.eigh(S)
    S = np.einsum("eij,ej,ekj->eik", vectors, np.exp(values), vectors)      # stretched and compressed
    F = Q @ S
    near = np.linalg.norm(np.einsum("eji,ejk->eik", F, F) - np.eye(3), axis=(1, 2)) <= 0.5
    assert 40 < near.sum() < len(F) - 40          # both iterations are exercised
    mat3 = ti.types.matrix(3, 3, ti.f64)
    a, out = ti.ndarray(mat3, len(F)), ti.ndarray(mat3, len(F))
    a.from_numpy(F)
    _polar_kernel(a, out)
    expected = np.stack([scipy.linalg.polar(f)[0] for f in F])
    assert np.abs(out.to_numpy() - expected).max() <= 1e-13


@ti.kernel
def _eigen_kernel(a: ti.types.ndarray(), values: ti.types.ndarray(), vectors: ti.types.ndarray()):
    for i in range(a.shape[0]):
        values[i], vectors[i] = symmetric_eigen(a[i])


def test_symmetric_eigen_matches_numpy(backend):
    """The Jacobi eigensolver of the polar rotation's inverted case, the compression limit and the
    energy, against numpy's eigh: random symmetric matrices of mixed sign, ones with a double or
    triple eigenvalue, nearly coincident ones and already diagonal ones. Eigenvalues to 1e-13 of
    the matrix's norm; V orthonormal and A V = V Λ to 1e-13 (eigenvectors of a repeated eigenvalue
    are any basis of its space, so they are checked through A V = V Λ, not against numpy's)."""
    rng = np.random.default_rng(11)
    Q = Rotation.random(40, random_state=12).as_matrix()
    spectra = np.concatenate([rng.normal(size=(10, 3)), np.repeat(rng.normal(size=(10, 1)), 3, axis=1),
                              np.stack([np.full(10, 2.0), np.full(10, 2.0), rng.normal(size=10)], axis=1),
                              1.0 + np.stack([np.zeros(10), np.full(10, 1e-9), rng.normal(size=10)], axis=1)])
    A = np.einsum("eij,ej,ekj->eik", Q, spectra, Q)
    A = np.concatenate([A, np.stack([np.diag(d) for d in rng.normal(size=(4, 3))])])
    mat3, vec3 = ti.types.matrix(3, 3, ti.f64), ti.types.vector(3, ti.f64)
    a, values, vectors = ti.ndarray(mat3, len(A)), ti.ndarray(vec3, len(A)), ti.ndarray(mat3, len(A))
    a.from_numpy(A)
    _eigen_kernel(a, values, vectors)
    lam, V = values.to_numpy(), vectors.to_numpy()
    scale = np.linalg.norm(A, axis=(1, 2))[:, None]
    assert np.abs(np.sort(lam, axis=1) - np.linalg.eigvalsh(A)).max() <= 1e-13 * scale.max()
    assert np.abs(np.einsum("eji,ejk->eik", V, V) - np.eye(3)).max() <= 1e-13
    assert (np.abs(A @ V - V * lam[:, None, :]) / scale[:, None]).max() <= 1e-13
