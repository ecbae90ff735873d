"""tissue.backend's choices, each in a fresh process: Taichi's IR passes, read from the environment; the arch "auto"."""

import os
import subprocess
import sys

import pytest

CODE = ("import taichi as ti\nfrom tissue import backend\nbackend.init('cpu')\n"
        "from tissue import compilation\n"
        "print('PASSES', ti.lang.impl.current_cfg().advanced_optimization, compilation._per_kernel)\n"
        "print('CACHE', ti.lang.impl.current_cfg().offline_cache_max_size_of_files == backend.OFFLINE_CACHE_BYTES)\n")


# Taichi's process-wide setting, and whether kernels marked without_ir_passes are compiled without
@pytest.mark.parametrize("value, expected", [(None, "False False"), ("auto", "True True"), ("0", "False False"),
                                             ("1", "True False")])
def test_advanced_optimization_follows_the_environment(value, expected):
    env = {k: v for k, v in os.environ.items() if k != "TISSUE_ADVANCED_OPTIMIZATION"}
    if value is not None:
        env["TISSUE_ADVANCED_OPTIMIZATION"] = value
    done = subprocess.run([sys.executable, "-c", CODE], env=env, capture_output=True, text=True, timeout=120)
    assert f"PASSES {expected}" in done.stdout and "CACHE True" in done.stdout, done.stdout + done.stderr


def test_a_bad_value_is_named():
    env = dict(os.environ, TISSUE_ADVANCED_OPTIMIZATION="yes")
    done = subprocess.run([sys.executable, "-c", CODE], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "TISSUE_ADVANCED_OPTIMIZATION: expected auto, 0 or 1, got 'yes'" in done.stderr


def test_auto_arch_skips_the_cuda_trial_only_where_taichi_could_not_load_the_driver():
    """In a fresh process: Taichi's own trial start on CUDA (what "auto" ran before it looked for the
    driver) lands on CUDA only where the driver library loads, and "auto" then lands where the trial
    does."""
    code = ("import taichi as ti\nfrom tissue import backend\n"
            "ti.init(arch=ti.cuda, log_level=ti.ERROR); trial = ti.lang.impl.current_cfg().arch == ti.cuda; ti.reset()\n"
            "loads = backend._cuda_driver_loads()\n"
            "print('AGREE', trial <= loads, backend.init('auto').arch == ('cuda' if trial else 'cpu'))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "AGREE True True" in done.stdout, done.stdout + done.stderr
