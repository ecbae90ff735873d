"""Taichi's IR passes chosen per kernel (TISSUE_ADVANCED_OPTIMIZATION=auto,
tissue.compilation.without_ir_passes): a marked kernel instance is compiled exactly as with the
passes off, the others exactly as with them on; a step computed either way agrees to round-off.

Taichi hashes the compile config (advanced_optimization included) into a kernel's offline-cache
key, so the cache files tell, independently of tissue's bookkeeping, which setting compiled each
kernel: a kernel compiled with a setting another process already compiled it with is a cache hit
(no new file); another setting is a new file.
"""

import os
import subprocess
import sys

import numpy as np
import pytest

SCRIPT = """
import sys
import numpy as np
import taichi as ti
from tissue import backend, compilation
backend.init("cpu")

@compilation.without_ir_passes(lambda a, scale: scale == 2.0)    # this instance only
@ti.kernel
def marked(a: ti.types.ndarray(), scale: ti.template()):
    for i in range(a.shape[0]):
        a[i] = a[i] * scale + 1.0

@ti.kernel
def plain(a: ti.types.ndarray()):
    for i in range(a.shape[0]):
        a[i] = a[i] * 3.0 - 1.0

a = np.linspace(0.0, 1.0, 5)
for _ in range(2):        # the second launch finds the kernel compiled at the first
    marked(a, 2.0)
    marked(a, 3.0)
    plain(a)
print("RESULT", " ".join(repr(float(v)) for v in a))
"""


def _run(tmp_path, setting):
    """Run SCRIPT with the Taichi cache in tmp_path/cache: the cache's kernel files, the result line."""
    cache, script = tmp_path / "cache", tmp_path / "kernels.py"    # Taichi reads a kernel's source file
    script.write_text(SCRIPT)
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache), TISSUE_ADVANCED_OPTIMIZATION=setting)
    done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = next(line for line in done.stdout.splitlines() if line.startswith("RESULT"))
    return {p.name for p in cache.glob("*.tic")}, result


def test_a_marked_kernel_instance_compiles_without_the_passes_the_others_with(tmp_path):
    off, result_off = _run(tmp_path, "0")
    assert len(off) == 3                                # three instances, passes off
    per_kernel, result_auto = _run(tmp_path, "auto")
    assert off <= per_kernel and len(per_kernel) == 5   # marked(2.0) found as compiled off; the others new
    on, result_on = _run(tmp_path, "1")
    assert per_kernel <= on and len(on) == 6            # marked(2.0) new (on); the others found as on
    again, _ = _run(tmp_path, "auto")
    assert again == on                                  # auto's three instances, all cached: nothing new
    expected = np.linspace(0.0, 1.0, 5)
    for _ in range(2):
        expected = (((expected * 2.0 + 1.0) * 3.0 + 1.0) * 3.0) - 1.0
    assert result_off == result_auto == result_on == "RESULT " + " ".join(repr(float(v)) for v in expected)


STEPS = """
import sys
import numpy as np
from scipy.spatial.transform import Rotation
from tissue import backend
backend.init("cpu")
from tissue.fem import CorotationalFEM, Material
from tissue.mesh import beam
from tissue.solver import CGSettings, ImplicitEuler

mesh = beam(1.0, 0.2, 0.2, cells_along=6, cells_across=2)
rng = np.random.default_rng(1)
x0 = mesh.points @ Rotation.from_rotvec([0.5, 1.2, -0.7]).as_matrix().T + 0.02 * rng.standard_normal(mesh.points.shape)
v0 = 0.1 * rng.standard_normal(mesh.points.shape)
out = {"x0": x0}
for preconditioner in ("none",):
    fem = CorotationalFEM(mesh, Material(young=1e5, poisson=0.3, density=1000.0), rotation="polar")
    solver = ImplicitEuler(fem, dt=0.01, rayleigh_mass=0.5, rayleigh_stiffness=0.02, execution="serial",
                           cg=CGSettings(max_iterations=300, tolerance=1e-12, preconditioner=preconditioner),
                           fixed=np.flatnonzero(mesh.points[:, 0] < 1e-12))
    solver.set_state(x0, v0)
    for _ in range(3):
        solver.step()
    out[preconditioner] = solver.positions()
np.savez(sys.argv[1], **out)
"""


@pytest.mark.slow   # compiles the serial step kernel with the passes: tens of seconds
def test_steps_with_and_without_the_passes(tmp_path):
    """Three serial steps of the test beam (CG to 1e-12) with the passes per kernel (auto: the "none"
    scheme's step kernel compiles with them) against none: round-off apart (measured 5.2e-14 of
    the displacement), not bit-identical. A multigrid scheme's step kernel compiles without them
    under auto, so exactly as with none (the cache-key test above)."""
    script = tmp_path / "steps.py"
    script.write_text(STEPS)
    results = {}
    for setting in ("0", "auto"):
        env = dict(os.environ, TISSUE_ADVANCED_OPTIMIZATION=setting)
        out = tmp_path / f"{setting}.npz"
        done = subprocess.run([sys.executable, str(script), str(out)], env=env, capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr
        results[setting] = np.load(out)
    off, auto = results["0"], results["auto"]
    change = np.linalg.norm(off["none"] - off["x0"])       # the three steps' displacement
    print("none: relative difference", np.linalg.norm(auto["none"] - off["none"]) / change)
    assert np.linalg.norm(auto["none"] - off["none"]) <= 1e-12 * change
