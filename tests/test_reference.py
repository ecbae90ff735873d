"""The rest compliance A₀⁻¹ of the contact layer (tissue.solver.reference.rest_compliance), inverted
through its Cholesky factor, against scipy's LU inverse of the same matrix."""

import numpy as np
import pytest
import scipy.linalg

from tissue.errors import TissueError
from tissue.fem import Material
from tissue.mesh import TetMesh, box
from tissue.solver.reference import free_dofs, rest_compliance, rest_matrix

MESH = box(size=(0.1, 0.05, 0.04), cells=(5, 3, 2))
MATERIAL = Material(3e3, 0.45, 300.0)


@pytest.mark.parametrize("fixed, rayleigh", [((), (0.0, 0.0)), (tuple(range(0, 72, 5)), (0.1, 0.01))])
def test_rest_compliance_is_the_inverse_of_the_rest_matrix(fixed, rayleigh):
    C = rest_compliance(MESH, MATERIAL, 0.04, fixed=fixed, rayleigh_mass=rayleigh[0], rayleigh_stiffness=rayleigh[1])
    A = rest_matrix(MESH, MATERIAL, 0.04, *rayleigh)
    free = free_dofs(MESH.n_points, fixed)
    expected = np.zeros_like(C)
    expected[np.ix_(free, free)] = scipy.linalg.inv(A[free][:, free].toarray())
    assert np.abs(C - expected).max() <= 1e-10 * np.abs(expected).max()
    assert np.array_equal(C, C.T)
    held = np.setdiff1d(np.arange(3 * MESH.n_points), free)
    assert not C[held].any() and not C[:, held].any()


def test_rest_compliance_names_a_node_of_no_element():
    """A point no tetrahedron uses has no mass and no stiffness: A₀ is singular there."""
    points = np.vstack([MESH.points, [[1.0, 1.0, 1.0]]])
    mesh = TetMesh(points, MESH.tets, source="box with a stray point")
    with pytest.raises(TissueError, match=rf"box with a stray point: .*not positive definite.*node {MESH.n_points}\b"):
        rest_compliance(mesh, MATERIAL, 0.04)
