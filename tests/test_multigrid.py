"""The two-level preconditioner (tissue.solver.multigrid) against independent references: its
matrix, built column by column from unit vectors, checked symmetric positive definite with numpy;
PCG with it against the scipy direct solve (test_solver's DEFAULT_CONFIGS, and the Vulkan run there);
its iteration counts against block-Jacobi's on a slender stiff beam."""

import numpy as np
import pytest

from test_solver import BEAM, FIXED, cantilever_tip, standard_state
from tissue.errors import TissueError
from tissue.fem import CorotationalFEM, Material
from tissue.solver import CGSettings, ImplicitEuler
from tissue.solver import reference as ref


def test_preconditioner_is_symmetric_positive_definite(solver):
    """Reference: numpy's symmetric eigensolver. The preconditioner B of a step from a state turned
    by 1.5 rad with 2 cm random strain (so element and nodal rotations differ from node to node),
    applied to every unit vector of the free dofs, is symmetric to round-off (measured 2e-16
    relative) and positive definite (smallest eigenvalue measured 0.02 of the largest 4.3)."""
    sim = solver(execution="parallel", preconditioner="multigrid")   # shared with test_solver
    x0, v0 = standard_state(1)
    sim.set_state(x0, v0)
    sim.step()
    n = BEAM.n_points
    free = ref.free_dofs(n, FIXED)
    unit = np.eye(3 * n)
    B = np.stack([sim.multigrid.apply_numpy(unit[i].reshape(n, 3)).reshape(-1)[free] for i in free], axis=1)
    assert np.abs(B - B.T).max() <= 1e-13 * np.abs(B).max()
    eigenvalues = np.linalg.eigvalsh(0.5 * (B + B.T))
    assert eigenvalues.min() > 1e-3 * eigenvalues.max()


def test_multigrid_needs_far_fewer_iterations_on_a_slender_beam(backend):
    """Reference: the stiff quasi-static cantilever of test_solver (40 cells along, 410 nodes,
    condition number ~10⁵) solved to 1e-10 (on rᵀB r) with block-Jacobi and with multigrid: both
    equal the scipy static solve to 1e-8 (measured 9e-11 and 7e-11; multigrid's ‖r‖/‖b‖ is 2e-8,
    its stopping rule measures the residual in B's norm), and multigrid needs at most a tenth of
    Jacobi's iterations (measured: 21 against 464)."""
    w_jac, w_static, it_jac, _ = cantilever_tip(40, "jacobi")
    w_mg, _, it_mg, _ = cantilever_tip(40, "multigrid")
    assert w_jac == pytest.approx(w_static, rel=1e-8)
    assert w_mg == pytest.approx(w_static, rel=1e-8)
    assert it_mg <= it_jac / 10


@pytest.mark.parametrize("kwargs,name", [(dict(coarse_nodes=4), "coarse_nodes"), (dict(coarse_nodes=1.5e3), "coarse_nodes"),
                                         (dict(smoothing_degree=0), "smoothing_degree")])
def test_multigrid_settings_are_checked(kwargs, name):
    with pytest.raises(TissueError, match=name):
        CGSettings(preconditioner="multigrid", **kwargs)


def test_multigrid_refuses_the_matrix_free_operator(backend):
    """The smoother multiplies by the assembled block rows, which matrix-free mode does not keep."""
    with pytest.raises(TissueError, match="multigrid"):
        ImplicitEuler(CorotationalFEM(BEAM, Material(1e5, 0.3, 1000.0)), 0.01, operator="matrix_free",
                      cg=CGSettings(preconditioner="multigrid"))
