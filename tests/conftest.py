"""Taichi is initialised once per test session (CPU, float64 unless TISSUE_ARCH says otherwise);
the offline cache stays on so the suite does not spend its time compiling."""

import os

import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")


@pytest.fixture(scope="session")
def backend():
    from tissue import backend as be

    return be.init(arch=os.environ.get("TISSUE_ARCH", "cpu"), precision="f64")
