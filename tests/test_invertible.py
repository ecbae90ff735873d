"""The "invertible" element (tissue.fem.compression_limit: the polar rotation of Irving et al. 2004 plus
a compression limit in its diagonal frame) against references the kernels did not produce: the
"polar" element where nothing is compressed, the numpy model of bench/nonlinear_reference.py (its
own SVD, its energy differenced), the direction that un-inverts an element, and the static
equilibrium that Newton finds for the same model."""

import numpy as np
import pytest

from bench import stability
from bench.nonlinear_reference import Body, internal_forces, solve_static, strain_energy
from tissue.fem import CorotationalFEM, Material
from tissue.fem.compression_limit import COMPRESSION_LIMIT
from tissue.mesh import beam
from tissue.mesh.tetmesh import signed_volumes
from tissue.solver import CGSettings, ImplicitEuler
from tissue.solver import reference as ref

MESH = beam(1.0, 0.2, 0.2, cells_along=6, cells_across=2)
MATERIAL = Material(young=1e5, poisson=0.3, density=1000.0)
FIXED = np.flatnonzero(MESH.points[:, 0] < 1e-12)


@pytest.fixture(scope="module")
def fems(backend):
    return {r: CorotationalFEM(MESH, MATERIAL, rotation=r) for r in ("polar", "invertible")}


def rotated_and_strained(seed, noise=0.005):
    """A 1.5 rad rotation plus 5 mm random displacements (elements 0.1-0.17 m across)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    Q = Rotation.from_rotvec([0.5, 1.2, -0.7]).as_matrix()
    return MESH.points @ Q.T + noise * rng.standard_normal(MESH.points.shape)


def mirrored(x):
    """The beam's far half mirrored through its mid-plane z = 0: every element there inside out."""
    x = x.copy()
    x[MESH.points[:, 0] > 0.5 + 1e-9, 2] *= -1
    return x


def singular_values(x):
    body = Body(MESH, MATERIAL, FIXED)
    from bench.nonlinear_reference import deformation_gradients

    return np.linalg.svd(deformation_gradients(body, x[MESH.tets]), compute_uv=False)


def test_equals_polar_where_no_element_is_compressed_past_the_limit(fems):
    """Reference: the "polar" element. With every singular value above the limit c the two are
    the same formula: forces, rotations and stiffness products agree to round-off (1e-13 of the
    largest force), and no element's tangent is stiffened."""
    x = rotated_and_strained(1)
    assert singular_values(x).min() > COMPRESSION_LIMIT + 0.1
    f_polar = fems["polar"].elastic_forces_numpy(x)
    f_inv = fems["invertible"].elastic_forces_numpy(x)
    assert np.abs(f_inv - f_polar).max() <= 1e-13 * np.abs(f_polar).max()
    np.testing.assert_allclose(fems["invertible"].rotations(), fems["polar"].rotations(), rtol=0, atol=1e-14)
    assert not fems["invertible"].work_arrays["limited"].to_numpy()[:MESH.n_tets].any()
    p = np.random.default_rng(2).standard_normal(x.shape)
    k_polar, k_inv = fems["polar"].stiffness_product_numpy(p), fems["invertible"].stiffness_product_numpy(p)
    assert np.abs(k_inv - k_polar).max() <= 1e-13 * np.abs(k_polar).max()


@pytest.mark.parametrize("state", ["mirrored", "squashed"])
def test_forces_match_the_numpy_model_and_its_differenced_energy(fems, state):
    """References: bench.nonlinear_reference's "invertible" model (numpy's SVD with the smallest
    singular value negated, against the kernels' Newton polar factor and Jacobi eigenvalues),
    to 1e-9 of the largest force; and that model's forces against its energy differenced
    (central, 1e-7 m steps) along a random direction, to 1e-6 relative. States: the far half
    mirrored (inverted elements), and the beam squashed to 0.2 of its height (compressed past the
    limit without inversion)."""
    x = mirrored(MESH.points) if state == "mirrored" else MESH.points * [1.0, 1.0, 0.2]
    x = x + 1e-3 * np.random.default_rng(3).standard_normal(x.shape)
    body = Body(MESH, MATERIAL, FIXED)
    expected = internal_forces(body, "invertible", x)
    assert np.abs(expected - internal_forces(body, "polar", x)).max() > 0.1 * np.abs(expected).max()  # the limit acts
    got = fems["invertible"].elastic_forces_numpy(x)
    assert np.abs(got - expected).max() <= 1e-9 * np.abs(expected).max()
    d = np.random.default_rng(4).standard_normal(x.shape)
    h = 1e-7
    differenced = -(strain_energy(body, "invertible", x + h * d) - strain_energy(body, "invertible", x - h * d)) / (2 * h)
    assert abs(differenced - (expected * d).sum()) <= 1e-6 * abs(differenced)


@pytest.mark.parametrize("rotation", ["polar", "invertible"])
def test_inverted_element_is_pushed_toward_uninverting(backend, rotation):
    """One tetrahedron with its apex pushed through the opposite face and sheared (distinct
    singular values, the smallest negated): the force on the apex points back out of the face,
    the forces raise the signed volume and lower the energy (of the numpy model, whose forces
    they equal)."""
    from tissue.mesh import TetMesh

    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    tet = TetMesh(X, np.array([[0, 1, 2, 3]]))
    x = X.copy()
    x[3] = [0.2, 0.1, -0.5]
    fem = CorotationalFEM(tet, MATERIAL, rotation=rotation)
    f = fem.elastic_forces_numpy(x)
    assert f[3, 2] > 0.0
    assert signed_volumes(x + 1e-3 * f / np.abs(f).max(), tet.tets)[0] > signed_volumes(x, tet.tets)[0]
    body = Body(tet, MATERIAL, np.zeros(0, dtype=np.int64))
    step = 1e-3 / np.abs(f).max()
    assert strain_energy(body, rotation, x + step * f) < strain_energy(body, rotation, x)
    np.testing.assert_allclose(f, internal_forces(body, rotation, x), rtol=0, atol=1e-9 * np.abs(f).max())


def squeezed_tet(a):
    """One tetrahedron with F = diag(a, 1, 1) (a < 0: inverted through the plane x = 0)."""
    from tissue.mesh import TetMesh

    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return TetMesh(X, np.array([[0, 1, 2, 3]])), X * [a, 1.0, 1.0]


def test_limit_is_a_barrier_with_the_quadratic_limit_as_its_expansion(backend):
    """The compression limit's energy along uniaxial compression F = diag(a, 1, 1), where the
    polar part is V (λ/2 + μ)(a − 1)² in closed form: near c it is the quadratic limit
    κ/2 (a − c)² to within a relative (c − a)/c; at a = BARRIER_END c it is the barrier
    κ c² (s − 1)²/(2s), s = a/c (which grows without bound as a → 0; its tangent line takes
    over below), c/a times the quadratic limit there; the kernels' force on the squeezed corner
    is the energy's derivative (numpy energy of tissue.fem.energy, central differences) on both
    sides of BARRIER_END and inverted, and their stiffness product (with the barrier's curvature)
    the force's."""
    from tissue.fem.compression_limit import BARRIER_END, COMPRESSION_STIFFNESS
    from tissue.fem.energy import element_energies
    from tissue.fem.model import BodyModel

    c = COMPRESSION_LIMIT
    lam, mu = MATERIAL.lame
    kappa = COMPRESSION_STIFFNESS * (lam + 2 * mu)

    def limit(a):
        tet, x = squeezed_tet(a)
        model = BodyModel(tet, MATERIAL)
        return element_energies(model, x, "invertible")[0] / (1 / 6) - (0.5 * lam + mu) * (a - 1) ** 2

    for h in (1e-2, 1e-3):
        assert limit(c - h) == pytest.approx(0.5 * kappa * h * h, rel=2 * h / c)
    assert limit(c + 1e-3) == 0.0
    a = BARRIER_END * c
    assert limit(a) == pytest.approx(kappa * c * c * (a / c - 1) ** 2 / (2 * a / c), rel=1e-12)
    for a in (0.5 * c, 1.01 * BARRIER_END * c, 0.99 * BARRIER_END * c, 1e-3, -0.3):
        tet, x = squeezed_tet(a)
        model = BodyModel(tet, MATERIAL)
        force = CorotationalFEM(tet, MATERIAL, rotation="invertible").elastic_forces_numpy(x)[1, 0]
        step = 1e-6
        plus, minus = x.copy(), x.copy()
        plus[1, 0] += step
        minus[1, 0] -= step
        energy = [element_energies(model, y, "invertible")[0] for y in (plus, minus)]
        differenced = -(energy[0] - energy[1]) / (2 * step)
        assert force > 0.0                                  # pushes the corner back out
        assert force == pytest.approx(differenced, rel=1e-6)
        # The tangent (directions held fixed) is the exact Jacobian along this motion: F stays
        # diagonal, so neither the rotation nor the principal directions turn.
        fem = CorotationalFEM(tet, MATERIAL, rotation="invertible")
        p = np.zeros_like(x)
        p[1, 0] = 1.0
        jacobian = (fem.elastic_forces_numpy(x + step * p) - fem.elastic_forces_numpy(x - step * p)) / (2 * step)
        fem.elastic_forces_numpy(x)                         # the rotations and the limit at x
        np.testing.assert_allclose(fem.stiffness_product_numpy(p), jacobian, rtol=0, atol=1e-6 * np.abs(jacobian).max())


# The tests that step a solver with "invertible" compile its whole step, for minutes on this
# machine (the eigen-solves inline in every kernel): slow set. The element's tests above run by default.
@pytest.mark.slow
def test_step_matches_the_direct_solve_of_polar_where_nothing_is_compressed(backend):
    """Reference: scipy's direct solve of the "polar" step (tissue.solver.reference) from a state
    with no element past the limit, where the two elements are one: 1e-8 relative, as
    test_solver's configurations."""
    step = dict(dt=0.01, gravity=(0.0, -3.0, -9.81), rayleigh_mass=0.5, rayleigh_stiffness=0.02)
    x0 = rotated_and_strained(1)
    v0 = 0.1 * np.random.default_rng(5).standard_normal(x0.shape)
    sim = ImplicitEuler(CorotationalFEM(MESH, MATERIAL, rotation="invertible"), fixed=FIXED,
                        cg=CGSettings(max_iterations=300, tolerance=1e-12), **step)
    sim.set_state(x0, v0)
    sim.step()
    x_ref, v_ref = ref.reference_step(MESH, MATERIAL, x0, v0, fixed=FIXED, rotation="polar", **step)
    assert np.linalg.norm(sim.velocities() - v_ref) <= 1e-8 * np.linalg.norm(v_ref)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["node", "mirror"])
def test_inverted_beam_recovers_to_an_equilibrium(backend, mode):
    """The stability matrix's inverted cantilevers (E 1e4 Pa, ν 0.45, dt 0.04 s, Rayleigh
    0.1/0.1, CG 25): one node pushed out through the body (6 elements inside out), or the far half
    mirrored (108 of 240), stepped with "invertible" until at rest (speed < 1e-9 m/s; at most
    120 s). No element is left inverted, and the rest is an equilibrium of the numpy model
    (bench.nonlinear_reference: internal forces balance the weight to 1e-6 of it). With the node,
    it is the equilibrium Newton finds from the rest shape, to 1e-6 of the tip's deflection. The
    mirrored half may un-invert into another equilibrium (the limit's energy keeps its elements
    from passing back through flat, where "polar" lets them: with an earlier, stiffer tangent it
    settled 0.84 of the deflection away), so the test pins it only as an equilibrium."""
    mesh = stability._mesh()
    material = Material(1e4, 0.45, 1000.0)
    cell = dict(case="inverted", mode=mode, dt=0.04, rotation="invertible")
    x, v, fixed = stability.initial_state(cell, mesh)
    assert (signed_volumes(x, mesh.tets) <= 0).sum() == {"node": 6, "mirror": 108}[mode]
    solver = stability.solver_for(cell, mesh, material)
    solver.set_fixed(fixed)
    solver.set_state(x, v)
    for _ in range(3000):     # until at rest (the mirror: speed 8e-10 m/s after 400 steps)
        solver.step()
        if np.abs(solver.velocities()).max() < 1e-9:
            break
    x, v = solver.positions(), solver.velocities()
    assert (signed_volumes(x, mesh.tets) <= 0).sum() == 0
    assert np.abs(v).max() < 1e-9
    body = Body(mesh, material, fixed)
    load = body.lumped_mass[:, None] * np.asarray(stability.GRAVITY)
    residual = (internal_forces(body, "invertible", x) + load).ravel()[body.free]
    assert np.linalg.norm(residual) <= 1e-6 * np.linalg.norm(load.ravel()[body.free])
    if mode == "node":
        static = solve_static(body, "invertible", load).x
        deflection = np.abs(static - mesh.points).max()
        assert np.abs(x - static).max() <= 1e-6 * deflection
