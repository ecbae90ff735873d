"""The solver's kernels on another Taichi arch and in float32, each run in a subprocess (Taichi
takes one arch and one precision per process) against this process's CPU float64 run of the same
steps. In a file of their own so that `make test` (a test file per worker) runs them beside
test_solver.py rather than after it."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from test_solver import BEAM, FIXED, MATERIAL, STEP, TIGHT, make_solver, rel, standard_state
from tissue.errors import TissueError
from tissue.solver import CGSettings
from tissue.solver import reference as ref


# --- 9. other arches --------------------------------------------------------------------------

def three_steps(arch, execution="parallel", rotation="large", preconditioner="none"):
    """Run by a subprocess with TISSUE_ARCH=arch: 3 steps of the standard problem (parallel
    execution: the GPU path), positions saved to the file named by argv[1]."""
    from tissue import backend
    try:
        backend.init(arch=arch, precision="f64")
    except TissueError as error:
        print(f"UNAVAILABLE: {error}")
        sys.exit(3)
    sim = make_solver(rotation, "gather", execution, preconditioner=preconditioner)
    x0, v0 = standard_state(4)
    sim.set_state(x0, v0)
    np.save(sys.argv[1], sim.run(3))


def run_on_arch(arch, execution, tmp_path, rotation="large", preconditioner="none"):
    """Positions after three_steps on `arch` in a subprocess (Taichi takes one arch per process)."""
    from taichi._lib import core
    if arch == "cuda" and not core.with_cuda():
        pytest.skip("taichi reports no CUDA on this machine")
    out = tmp_path / "positions.npy"
    code = f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); " \
           f"from test_arch_precision import three_steps; three_steps({arch!r}, {execution!r}, {rotation!r}, {preconditioner!r})"
    env = dict(os.environ, TISSUE_ARCH=arch, TISSUE_PRECISION="f64")
    done = subprocess.run([sys.executable, "-c", code, str(out)], env=env, capture_output=True,
                          text=True, timeout=600)
    if done.returncode == 3 and "UNAVAILABLE" in done.stdout:
        pytest.skip(done.stdout.strip())
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return np.load(out)


def cpu_three_steps(solver, rotation="large", preconditioner="none"):
    sim = solver(rotation, "gather", "parallel", "assembled", preconditioner)
    x0, v0 = standard_state(4)
    sim.set_state(x0, v0)
    return sim.run(3), x0


@pytest.mark.parametrize("rotation,preconditioner", [("large", "none"), ("polar", "none"), ("large", "multigrid")])
@pytest.mark.parametrize("arch", ["vulkan", "cuda"])
def test_other_arch_matches_cpu(solver, arch, rotation, preconditioner, tmp_path):
    """Reference: the CPU run of this process. The same 3 steps (large rotation, random strain and
    velocities, gravity, damping, clamped end; parallel execution) on `arch` in a subprocess:
    positions agree to 1e-9 relative to the displacement (the GPU path sums dot products in other
    blocks; measured on Mesa's lavapipe Vulkan: 1.8e-12 relative, 6e-14 m at worst). Skipped only when
    the arch is not available (CUDA needs a GPU). This test found taichi-dev/taichi#8803 (the
    63-node beam's last `fixed` flag overwritten on Vulkan, in Taichi fields; tissue keeps ndarrays
    now), and that "polar" needed a scaling without 64-bit pow (GLSL has none). With the multigrid preconditioner
    the same bound holds."""
    x_gpu = run_on_arch(arch, "parallel", tmp_path, rotation, preconditioner)
    x_cpu, x0 = cpu_three_steps(solver, rotation, preconditioner)
    assert np.linalg.norm(x_gpu - x_cpu) <= 1e-9 * np.linalg.norm(x_cpu - x0)


# --- 10. float32 ------------------------------------------------------------------------------

F32_CG_TOLERANCE = 1e-6     # ~8 float32 epsilons: CG in float32 reaches it (48 iterations), not much below


def f32_step():
    """Run by a subprocess (precision is chosen once per process): one step of the standard
    problem in float32, CG to F32_CG_TOLERANCE; positions and velocities saved to argv[1]."""
    from tissue import backend
    backend.init(arch="cpu", precision="f32")
    sim = make_solver("large", "gather", "serial", cg=CGSettings(TIGHT.max_iterations, F32_CG_TOLERANCE))
    x0, v0 = standard_state(1)
    sim.set_state(x0, v0)
    sim.step()
    assert sim.stats.counters["cg_residual"] <= F32_CG_TOLERANCE
    np.save(sys.argv[1], np.stack([sim.positions(), sim.velocities()]))


def test_float32_step_matches_float64(solver, tmp_path):
    """Reference: the same implicit-Euler step in float64 in this process (which matches the direct
    solve to 1e-8). Bound, from float32's epsilon and the step's conditioning: a linear solve's
    forward error is at most κ(A) times (the relative residual + the relative error of its data).
    κ(A) of M(1 + hα) + (hβ + h²)K on the free nodes is computed here (85); the data (elastic
    forces K(Rᵀx - X)) are formed in float32 from positions rounded to ε‖x‖, which the subtraction
    of X amplifies by ‖x‖/‖x - QX‖ (2 cm random displacements of a 1 m beam: 20 here). So
    ‖v32 - v64‖/‖v64‖ ≤ κ (tol + ε ‖x‖/‖x - QX‖) ≈ 3e-4; the step's displacement adds the rounding of
    the positions themselves, ε ‖x‖/‖Δx‖ (~9e-6). Measured: 5e-6 and 5e-6 (round-off errors do not
    all line up as the bound assumes); a float32 path that lost a term or its precision (say a
    float64 constant truncated, a force in half precision) is off by more than the bound."""
    out = tmp_path / "f32.npy"
    code = f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); from test_arch_precision import f32_step; f32_step()"
    env = dict(os.environ, TISSUE_ARCH="cpu", TISSUE_PRECISION="f32")
    done = subprocess.run([sys.executable, "-c", code, str(out)], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    x32, v32 = np.load(out)
    x0, v0 = standard_state(1)
    sim = solver("large", "gather", "serial", "assembled", "none")
    sim.set_state(x0, v0)
    sim.step()
    x64, v64 = sim.positions(), sim.velocities()

    eps = float(np.finfo(np.float32).eps)
    system = ref.linearise(BEAM, MATERIAL, x0, v0, rotation="large", **STEP)
    free = ref.free_dofs(BEAM.n_points, FIXED)
    kappa = np.linalg.cond(system.A[free][:, free].toarray())
    Q = Rotation.from_rotvec([0.5, 1.2, -0.7]).as_matrix()
    cancellation = np.linalg.norm(x0) / np.linalg.norm(x0 - BEAM.points @ Q.T)
    velocity_bound = kappa * (F32_CG_TOLERANCE + eps * cancellation)
    assert 50 < kappa < 200 and velocity_bound < 1e-3       # the problem is what the bound assumes
    assert rel(v32, v64) <= velocity_bound
    assert rel(x32 - x0, x64 - x0) <= velocity_bound + eps * np.linalg.norm(x0) / np.linalg.norm(x64 - x0)
    assert rel(v32, v64) > 1e-8       # it did run in float32 (float64 agrees to ~1e-12)
