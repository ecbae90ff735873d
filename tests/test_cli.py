"""The `tissue` command: in-process through `tissue.cli.main`, plus subprocess smoke tests."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from tissue.cli import main

# A coarse, short beam: every run test costs well under a few seconds.
FAST = ["--arch", "cpu", "--steps", "3", "--set", "beam.cells=6,1,1", "--set", "render.every=1"]


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_list_shows_the_three_scenes_with_their_description(capsys):
    code, out, _ = run(capsys, "list")
    assert code == 0
    lines = {line.split()[0]: line for line in out.splitlines() if line.strip()}
    assert {"beam", "liver", "organs"} <= set(lines)
    assert "cantilever" in lines["beam"].lower() and "liver" in lines["liver"].lower()


@pytest.mark.parametrize("override, message", [
    ("beam.yung=1", "beam.yung: unknown field; did you mean 'young'?"),
    ("beam.young=soft", "beam.young: expected a number, got 'soft'"),
    ("beam.poisson=0.5", "beam.poisson: Poisson's ratio must lie in (-1, 0.5)"),
    ("beam.young=0", "beam.young: Young's modulus must be > 0 Pa"),
    ("dt=0", "dt: the time step must be > 0 s"),
    ("beam.mesh=no/such/mesh.vtu", "beam.mesh: no such file 'no/such/mesh.vtu'"),
])
def test_bad_input_is_one_line_naming_the_field_and_exit_2(capsys, tmp_path, override, message):
    code, out, err = run(capsys, "run", "beam", "--no-render", "--out", str(tmp_path), "--set", override)
    assert code == 2
    assert err.count("\n") == 1 and message in err, err
    assert "Traceback" not in err


def test_unknown_scene_and_bad_steps(capsys, tmp_path):
    code, _, err = run(capsys, "run", "livr", "--out", str(tmp_path))
    assert code == 2 and "livr: unknown scene; did you mean 'liver'?" in err
    code, _, err = run(capsys, "run", "beam", "--steps", "0", "--out", str(tmp_path))
    assert code == 2 and "--steps" in err


def test_debug_shows_the_traceback(capsys, tmp_path):
    code, _, err = run(capsys, "run", "beam", "--debug", "--out", str(tmp_path), "--set", "beam.yung=1")
    assert code == 2 and "Traceback" in err and "beam.yung: unknown field" in err


def test_runtime_failure_exits_1(capsys, tmp_path, monkeypatch, backend):
    from tissue.errors import TissueError
    from tissue.simulation import Simulation

    def diverge(self):
        raise TissueError("beam: the simulation diverged")

    monkeypatch.setattr(Simulation, "step", diverge)
    code, _, err = run(capsys, "run", "beam", "--no-render", "--out", str(tmp_path), *FAST)
    assert code == 1 and err.strip() == "tissue: error: beam: the simulation diverged"


def test_run_without_render_writes_stats_and_a_pvd_and_keeps_other_files(capsys, tmp_path, backend):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, stdout, err = run(capsys, "run", "beam", "--no-render", "--out", str(out), *FAST)
    assert code == 0, err
    assert (out / "notes.txt").read_text() == "mine"
    stats = json.loads((out / "stats.json").read_text())
    assert stats["scene"] == "beam" and stats["steps"] == 3 and stats["stages"] == ["free_motion"]
    assert stats["ms_per_step"]["free_motion"] > 0 and "free_motion: step" in stats["ms_per_step"]
    assert stats["counters_last"]["cg_iterations"] >= 1
    assert stats["scene_settings"]["beam.cells"] == [6, 1, 1]
    pvd = (out / "vtu" / "beam.pvd").read_text()
    assert pvd.count("<DataSet") == 4  # steps 0..3
    assert not list(out.glob("*.png")) and not (out / "animation.gif").exists()
    assert "ms/step" in stdout and "free_motion" in stdout
    assert stats["kernel_compilation_seconds"] >= stats["kernel_compilation_seconds_in_steps"] >= 0
    assert stats["kernels_compiled"] >= 0 and stats["mesh_generation_seconds"] >= 0
    assert 0 <= stats["run_compile_seconds"] <= stats["run_seconds"]
    assert "kernel compilation" in stdout and f"({stats['kernels_compiled']} kernels: " in stdout
    assert stats["kernel_compilation_seconds"] == pytest.approx(
        stats["kernel_compilation_ir_seconds"] + stats["kernel_compilation_machine_code_seconds"], abs=1e-3)


def test_run_with_render_writes_a_non_blank_png(capsys, tmp_path, backend):
    out = tmp_path / "render"
    code, _, err = run(capsys, "run", "beam", "--out", str(out), *FAST, "--set", "render.size=320,240",
                       "--set", "render.animation_size=160,120", "--set", "render.outputs=png,gif")
    assert code == 0, err
    figure = np.asarray(Image.open(out / "figure.png").convert("RGB"))
    assert figure.shape == (240, 320, 3)
    coloured = np.abs(figure.astype(int) - 255).sum(axis=2) > 60
    assert coloured.mean() > 0.02, "the figure is (nearly) blank"
    assert {p.name for p in out.glob("frame_*.png")} == {"frame_000000.png", "frame_000002.png",
                                                         "frame_000003.png"}
    assert Image.open(out / "animation.gif").n_frames == 4


def test_show_prints_settings_with_overrides(capsys):
    code, out, _ = run(capsys, "show", "beam", "--set", "beam.young=5e5")
    assert code == 0 and "beam.young=500000.0" in out and "render.camera=front" in out


def test_info_names_backend_and_versions(capsys, backend):
    code, out, _ = run(capsys, "info", "--arch", "cpu")
    assert code == 0
    assert "backend    cpu" in out and "precision  f64" in out and "taichi 1.7" in out and "numpy" in out
    assert "IR passes  off" in out          # the default (bench/compile_options.py says why)


def _python(code: str, **kwargs):
    env = dict(os.environ, TISSUE_ARCH="cpu", PYVISTA_OFF_SCREEN="true")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=300, **kwargs)


def test_no_render_run_imports_neither_pyvista_nor_open3d_nor_contact(tmp_path):
    code = (
        "import sys\n"
        "from tissue.cli import main\n"
        f"rc = main(['run', 'beam', '--no-render', '--out', {str(tmp_path)!r}, '--steps', '2',"
        " '--set', 'beam.cells=4,1,1'])\n"
        "heavy = [m for m in ('pyvista', 'vtk', 'open3d', 'meshio', 'tissue.render', 'tissue.contact')"
        " if m in sys.modules]\n"
        "print('HEAVY', heavy, 'RC', rc)\n")
    result = _python(code)
    assert "HEAVY [] RC 0" in result.stdout, result.stdout + result.stderr


@pytest.mark.parametrize("given, used", [(None, "1"), ("2", "2")])
def test_the_command_runs_blas_on_one_thread_unless_told(given, used):
    """OPENBLAS_NUM_THREADS is read when numpy loads OpenBLAS: tissue.cli sets its default before
    numpy is imported, and leaves a value the user gave."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    code = "import os, sys\nimport tissue.cli\nprint('BLAS', os.environ['OPENBLAS_NUM_THREADS'], 'numpy' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert f"BLAS {used} False" in result.stdout, result.stdout + result.stderr


def test_python_dash_m_tissue_smoke(tmp_path):
    result = subprocess.run([sys.executable, "-m", "tissue", "run", "beam", "--set", "beam.yung=1",
                             "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == \
        "tissue: error: beam.yung: unknown field; did you mean 'young'?"


def test_a_second_run_with_other_settings_compiles_nothing(capsys, tmp_path, backend):
    """`tissue run` twice in one process, the second on another mesh size, time step, CG cap
    and friction: every kernel the second needs was compiled by the first (or by earlier tests in
    this process; stats.json counts the kernel instances compiled during a run)."""
    first, second = tmp_path / "first", tmp_path / "second"
    code, _, err = run(capsys, "run", "incline", "--no-render", "--out", str(first), "--arch", "cpu", "--steps", "3")
    assert code == 0, err
    code, stdout, err = run(capsys, "run", "incline", "--no-render", "--out", str(second), "--arch", "cpu",
                            "--steps", "3", "--set", "block.cells=3,5,2", "--set", "dt=0.004",
                            "--set", "solver.cg_iterations=40", "--set", "contact.friction=0.6")
    assert code == 0, err
    from tissue import compilation

    assert compilation.count() > 0          # the counter counts (tests/test_compilation.py checks it)
    stats = json.loads((second / "stats.json").read_text())
    assert stats["bodies"]["block"]["tets"] != 4 * 4 * 2 * 6
    assert stats["kernels_compiled"] == 0, stdout
