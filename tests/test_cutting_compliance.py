"""The cutting compliance against the direct inverse of the freshly assembled rest matrix, after
every edit of random cut sequences, eager and lazy (float64)."""

import numpy as np
import pytest
import scipy.linalg

from tissue.fem.material import Material
from tissue.fem.model import HELD, BodyModel
from tissue.mesh import box
from tissue.mesh.topology import OUTWARD_FACES
from tissue.solver.reference import rest_matrix

MATERIAL = Material(young=5000.0, poisson=0.35, density=1000.0)
DT, ALPHA_M, ALPHA_K = 0.01, 0.1, 0.02
TOLERANCE = 1e-8


def direct_inverse(model: BodyModel) -> np.ndarray:
    """A⁻¹ on the free dofs (held and detached nodes zero), assembled and inverted from scratch."""
    A = rest_matrix(model.mesh(), MATERIAL, DT, ALPHA_M, ALPHA_K)
    free = np.flatnonzero(np.repeat(model.held == 0, 3))
    C = np.zeros(A.shape)
    C[np.ix_(free, free)] = scipy.linalg.inv(A[free][:, free].toarray())
    return C


def relative_error(C: np.ndarray, reference: np.ndarray) -> float:
    return float(np.abs(C - reference).max() / np.abs(reference).max())


def make_body(cells, held_x0=True):
    model = BodyModel(box(size=(0.1, 0.08, 0.06), cells=cells), MATERIAL)
    if held_x0:
        model.set_held(np.flatnonzero(model.points[:, 0] == 0.0))
    return model


def compliances(model, lazy_fold_rank=60, blas=None):
    """Eager and lazy; `blas` False: the algebra in Taichi kernels (what other archs run), else
    numpy's BLAS on the same memory (the CPU's default)."""
    from tissue.cutting import CuttingCompliance

    return {"eager": CuttingCompliance(model, DT, ALPHA_M, ALPHA_K, blas=blas),
            "lazy": CuttingCompliance(model, DT, ALPHA_M, ALPHA_K, fold_rank=lazy_fold_rank, blas=blas)}


def split(model: BodyModel, elements) -> None:
    """Remove these elements and put each back as four around a new node at its centroid."""
    tets = model.tets[np.asarray(elements)].copy()
    model.remove_elements(elements)
    centres = model.add_nodes(model.points[tets].mean(axis=1))
    faces = tets[:, OUTWARD_FACES[:, ::-1]]                       # (k, 4, 3), apex inside
    model.add_elements(np.concatenate([faces, np.broadcast_to(centres[:, None, None], (len(tets), 4, 1))],
                                      axis=2).reshape(-1, 4))


def check(model, updates, step):
    reference = direct_inverse(model)
    for mode, update in updates.items():
        C = update.dense()
        error = relative_error(C, reference)
        assert error < TOLERANCE, f"{mode} after step {step}: relative error {error:.2e}"
        if update.rank == 0:            # folded: exactly symmetric (W = H C Hᵀ relies on it)
            assert np.array_equal(C, C.T), f"{mode} after step {step}: C not symmetric"


def test_initial_compliance_is_the_direct_inverse(backend):
    model = make_body((2, 2, 2))
    check(model, compliances(model), "0")


@pytest.mark.parametrize("seed, cells, blas", [(0, (2, 2, 2), None), (1, (3, 2, 2), None), (2, (3, 3, 2), None),
                                               (0, (2, 2, 2), False), (2, (3, 3, 2), False)])
def test_random_cuts_match_the_direct_inverse(backend, seed, cells, blas):
    rng = np.random.default_rng(seed)
    model = make_body(cells)
    updates = compliances(model, blas=blas)
    for step in range(6):
        chosen = rng.choice(model.n_elements, size=rng.integers(1, 4), replace=False)
        if rng.random() < 0.3:
            model.remove_elements(chosen)                 # a plain removal
        else:
            split(model, chosen)
        if step % 2 == 0:                                 # sometimes two edits in one update
            for update in updates.values():
                update.update()
        check(model, updates, step)
    assert updates["lazy"].folds < updates["eager"].folds     # lazy did keep its factors


@pytest.mark.parametrize("blas", [None, False])
def test_detached_and_held_nodes_have_zero_rows(backend, blas):
    model = make_body((2, 2, 2))
    updates = compliances(model, blas=blas)
    corner = int(np.flatnonzero((model.points == model.points.max(axis=0)).all(axis=1))[0])
    around = np.flatnonzero((model.tets == corner).any(axis=1))
    removed = model.tets[around].copy()
    model.remove_elements(around)
    assert model.held[corner] not in (0, HELD)                         # detached
    zero = np.repeat(np.concatenate([[corner], model.held_nodes]), 3)
    for mode, update in updates.items():
        C = update.dense()
        assert np.all(C[zero] == 0.0) and np.all(C[:, zero] == 0.0), mode
    check(model, updates, "detach")
    model.add_elements(removed)                                        # the corner free again
    assert model.held[corner] == 0
    check(model, updates, "reattach")


def test_a_wrong_sign_is_caught(backend):
    """The comparison can fail: the update with B's sign flipped is far from the direct inverse."""
    model = make_body((2, 2, 2))
    updates = compliances(model)
    eager = updates["eager"]
    split(model, [3])
    eager._pending = [(tets, -blocks) for tets, blocks in eager._pending]
    assert relative_error(eager.dense(), direct_inverse(model)) > 1e-3


def test_subtract_product_in_place_matches_numpy():
    """tissue.cutting.blas.subtract_product: C −= A Bᵀ on blocks of larger arrays (their row strides
    the BLAS's leading dimensions), against numpy, with nothing outside the block touched."""
    from tissue.cutting.blas import subtract_product

    rng = np.random.default_rng(3)
    C, T, U = rng.standard_normal((40, 50)), rng.standard_normal((40, 9)), rng.standard_normal((50, 9))
    for rows, cols, rank in [(slice(3, 17), slice(5, 41), 7), (slice(0, 40), slice(0, 50), 9), (slice(8, 9), slice(2, 3), 1)]:
        expected = C.copy()
        expected[rows, cols] -= T[rows, :rank] @ U[cols, :rank].T
        subtract_product(C[rows, cols], T[rows, :rank], U[cols, :rank])
        np.testing.assert_allclose(C, expected, rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="shapes"):
        subtract_product(C[:4, :5], T[:3, :2], U[:5, :2])
    with pytest.raises(ValueError, match="contiguous rows"):
        subtract_product(C[:4, :5], T[:4, :2], np.asfortranarray(U[:5, :2]))

