"""Taichi is initialised once per test session (CPU, float64 unless TISSUE_ARCH says otherwise);
the offline cache stays on so the suite does not spend its time compiling. Generated meshes are
cached in a folder of the session's own (unless TISSUE_CACHE is set), never in the user's home. `make test` runs a
session per core (pytest-xdist, a test file per worker), so session fixtures are per worker."""

import os

import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
# BLAS on one thread, as `tissue run` has it (tissue/cli.py): OpenBLAS's threads wait on Taichi's
# and on each other, and the dense set-up of a contact or cutting test then takes seconds. Read when
# numpy loads OpenBLAS: here, before any test module imports numpy.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@pytest.fixture(scope="session", autouse=True)
def mesh_cache(tmp_path_factory):
    if os.environ.get("TISSUE_CACHE"):
        yield
        return
    os.environ["TISSUE_CACHE"] = str(tmp_path_factory.mktemp("tissue-cache"))
    yield
    del os.environ["TISSUE_CACHE"]


@pytest.fixture(scope="session")
def backend():
    from tissue import backend as be

    return be.init(arch=os.environ.get("TISSUE_ARCH", "cpu"), precision="f64")


@pytest.fixture(scope="session")
def solver(backend):
    """solver(rotation, accumulation, execution, operator, preconditioner): one ImplicitEuler on
    test_solver's standard beam with its standard step (STEP, TIGHT), built once per configuration
    for the whole session: Taichi compiles kernels per solver object (~10-30 s each here), so tests
    that can share a configuration share one, resetting its state with `set_state`."""
    from test_solver import make_solver

    cache = {}

    def get(rotation="large", accumulation="gather", execution="serial", operator="assembled",
            preconditioner="none"):
        key = (rotation, accumulation, execution, operator, preconditioner)
        if key not in cache:
            cache[key] = make_solver(*key)
        return cache[key]

    return get
