"""tissue.backend's choice of Taichi's IR passes, read from the environment in a fresh process."""

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
