"""Offscreen rendering: PNG size and content, GIF/MP4 frames, colour bars, transparency, a camera
that stays put across frames, and updates that match a fresh render."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyvista")
from PIL import Image  # noqa: E402

from tissue.errors import TissueError  # noqa: E402
from tissue.mesh import TetMesh, boundary_faces  # noqa: E402

# A unit box by hand: 8 corners (index x + 2y + 4z), 6 positively oriented tetrahedra around the
# 0-7 diagonal; the renderer gets its 12 boundary triangles.
BOX = TetMesh(np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float),
              np.array([[0, 1, 3, 7], [0, 1, 7, 5], [0, 2, 7, 3], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 7, 6]]),
              source="test box")
BOX_POINTS = BOX.points
BOX_FACES = boundary_faces(BOX.tets)
SIZE = (320, 240)

ROOT = Path(__file__).resolve().parents[1]
_PROBE = """
import tissue.render  # picks the offscreen window class
import pyvista as pv
p = pv.Plotter(off_screen=True, window_size=[32, 32])
p.add_mesh(pv.Sphere())
assert p.screenshot(None, return_img=True).std() > 0
"""


@pytest.fixture(scope="module")
def offscreen():
    # Probe in a child process: without an EGL/OSMesa driver VTK may abort rather than raise.
    done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120,
                          cwd=ROOT)
    if done.returncode != 0:
        lines = re.sub(r"\x1b\[[0-9;]*m", "", done.stderr).strip().splitlines() or [f"exit {done.returncode}"]
        pytest.skip("offscreen rendering unavailable (VTK needs libEGL + libGL with Mesa's llvmpipe, "
                    "or libOSMesa; see SYSTEM_PACKAGES in the Makefile): " + lines[-1][-200:])


renders = pytest.mark.usefixtures("offscreen")


def reddish(rgb):
    rgb = rgb[..., :3].astype(int)
    return (rgb[..., 0] > rgb[..., 1] + 30) & (rgb[..., 0] > rgb[..., 2] + 30)


def box_renderer(size=SIZE, **kwargs):
    from tissue.render import Renderer

    r = Renderer(size=size, **kwargs)
    r.add_body("box", BOX_POINTS, BOX_FACES)
    return r


@renders
def test_png_has_size_and_shows_the_body(tmp_path):
    with box_renderer(camera="iso") as r:
        path = r.screenshot(tmp_path / "frames" / "box.png")
    img = np.asarray(Image.open(path))
    assert img.shape[:2] == (SIZE[1], SIZE[0])
    assert img.std() > 0
    assert reddish(img).mean() > 0.05  # the default tissue colour covers part of the frame
    assert (img[0, 0, :3] == 255).all()  # white background


@renders
def test_transparent_background_has_alpha(tmp_path):
    with box_renderer(background="transparent") as r:
        img = np.asarray(Image.open(r.screenshot(tmp_path / "box.png")))
    assert img.shape == (SIZE[1], SIZE[0], 4)
    corners = img[[0, 0, -1, -1], [0, -1, 0, -1], 3]
    assert (corners == 0).all()
    assert img[SIZE[1] // 2, SIZE[0] // 2, 3] == 255


@renders
def test_scalars_render_with_a_colour_bar(tmp_path):
    from tissue.render import Renderer

    with Renderer(size=SIZE, camera="front", up="z") as r:
        r.add_body("box", BOX_POINTS, BOX_FACES, scalars=BOX_POINTS[:, 2] * 30,
                   scalar_name="displacement (mm)", clim=(0, 30))
        r.add_body("other", BOX_POINTS + 2, BOX_FACES, scalars=np.arange(12.0),  # per triangle
                   scalar_name="von Mises (kPa)")
        img = np.asarray(Image.open(r.screenshot(tmp_path / "scalars.png")))
        assert set(r.plotter.scalar_bars.keys()) == {"displacement (mm)", "von Mises (kPa)"}
    # viridis' top colour (the bar's end, unlit) is present.
    assert (np.abs(img[..., :3].astype(int) - [253, 231, 37]).sum(-1) < 40).any()


@renders
def test_gif_has_its_frames_and_is_downscaled(tmp_path):
    with box_renderer(size=(640, 480)) as r:
        anim = r.animation(tmp_path / "box.gif", fps=10, gif_width=240)
        for k in range(3):
            r.update_body("box", BOX_POINTS * (1 + 0.2 * k))
            anim.write_frame(label=f"t = {k / 10:.1f} s")
        assert anim.close() == [tmp_path / "box.gif"]
    gif = Image.open(tmp_path / "box.gif")
    assert gif.n_frames == 3
    assert gif.size == (240, 180)


@renders
def test_gif_keeps_at_most_max_frames(tmp_path):
    with box_renderer() as r:
        with r.animation(tmp_path / "long.gif", max_gif_frames=4) as anim:
            for k in range(9):
                r.update_body("box", BOX_POINTS + [0.05 * k, 0, 0])  # Pillow merges identical frames
                anim.write_frame()
    assert Image.open(tmp_path / "long.gif").n_frames == 4


@renders
def test_mp4_written_or_skipped_with_a_message(tmp_path):
    with box_renderer() as r:
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            with pytest.warns(UserWarning, match="imageio-ffmpeg"):
                anim = r.animation(tmp_path / "box.mp4")
            anim.write_frame()
            assert anim.close() == []
            return
        with r.animation(tmp_path / "box.mp4", tmp_path / "box.gif") as anim:
            for k in range(3):
                r.update_body("box", BOX_POINTS + [0, 0, 0.1 * k])
                anim.write_frame()
    assert (tmp_path / "box.mp4").stat().st_size > 1000
    assert Image.open(tmp_path / "box.gif").n_frames == 3


@renders
def test_camera_stays_fixed_while_bodies_move():
    with box_renderer(camera="iso") as r:
        r.image()
        before = r.plotter.camera_position
        r.update_body("box", BOX_POINTS * 3 + 1)
        r.image()
        assert r.plotter.camera_position == before
        r.set_camera("top")
        assert r.plotter.camera_position != before


@renders
def test_updated_points_render_like_a_fresh_body():
    # Normals must follow the new points (smooth shading runs in the pipeline, not once).
    from tissue.render import Renderer

    moved = BOX_POINTS * [1.0, 1.5, 0.5] + 0.1
    bounds = (-1, 3, -1, 3, -1, 3)
    with box_renderer(bounds=bounds, ground=True) as r:
        r.image()
        r.update_body("box", moved)
        updated = r.image().astype(int)
    with Renderer(size=SIZE, bounds=bounds, ground=True) as fresh:
        fresh.add_body("box", moved, BOX_FACES)
        expected = fresh.image().astype(int)

    assert np.abs(updated - expected).mean() < 1.0


@renders
def test_obstacles_and_ground_render(tmp_path):
    import pyvista as pv

    bounds = (-1, 2, -1, 2, -1, 2)      # the same camera for both renders below
    with box_renderer(bounds=bounds, ground=True, title="box on a floor") as r:
        r.add_obstacle("ball", pv.Sphere(radius=0.3, center=(0.5, 0.5, 1.5)))
        r.add_obstacle("plate", (BOX_POINTS * [2, 2, 0.01] - [0.5, 0.5, 0.2], BOX_FACES))
        first = r.image()
        r.update_obstacle("ball", transform=np.array([[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0],
                                                      [0, 0, 0, 1.0]]))
        with_ball = r.image().astype(int)
        assert np.abs(with_ball - first.astype(int)).sum() > 0
        r.remove("ball")
        removed = r.image().astype(int)
    # After `remove`, the picture is the one drawn without the ball (and not the one with it).
    with box_renderer(bounds=bounds, ground=True, title="box on a floor") as fresh:
        fresh.add_obstacle("plate", (BOX_POINTS * [2, 2, 0.01] - [0.5, 0.5, 0.2], BOX_FACES))
        expected = fresh.image().astype(int)

    def changed(a, b):                  # share of pixels that differ visibly
        return (np.abs(a - b).sum(axis=-1) > 60).mean()

    assert changed(removed, expected) < 0.001
    assert changed(with_ball, expected) > 0.005      # the ball covers ~1 % of the picture


@renders
def test_bad_input_is_named():
    from tissue.render import Renderer

    with Renderer(size=SIZE) as r:
        with pytest.raises(TissueError, match="out of range"):
            r.add_body("box", BOX_POINTS, BOX_FACES + 8)
        r.add_body("box", BOX_POINTS, BOX_FACES, scalars=np.zeros(8))
        with pytest.raises(TissueError, match="neither"):
            r.update_body("box", scalars=np.zeros(5))
        with pytest.raises(TissueError, match="no body named"):
            r.update_body("liver", BOX_POINTS)
        with pytest.raises(TissueError, match="preset"):
            r.set_camera("diagonal")
        with pytest.raises(TissueError, match=".gif or .mp4"):
            r.animation("out.avi")


@pytest.mark.parametrize("preset", ["iso", "front", "side", "top", (120.0, -30.0)])
@pytest.mark.parametrize("up", ["y", "z", "-z"])
def test_presets_frame_the_whole_box(preset, up):
    from tissue.render.camera import camera_position

    bounds = (0, 4, -1, 1, 0, 0.5)
    position, focal, view_up = map(np.asarray, camera_position(bounds, preset, up, aspect=4 / 3))
    forward = (focal - position) / np.linalg.norm(focal - position)
    right = np.cross(forward, view_up)
    corners = np.array(np.meshgrid(*np.reshape(bounds, (3, 2)), indexing="ij")).reshape(3, -1).T
    rel = corners - position
    depth = rel @ forward
    assert (depth > 0).all()
    tan_v = np.tan(np.radians(15))
    assert (np.abs(rel @ view_up) / depth <= tan_v * 1.0001).all()
    assert (np.abs(rel @ right) / depth <= tan_v * 4 / 3 * 1.0001).all()


def test_import_tissue_does_not_import_pyvista():
    code = "import sys, tissue; assert 'pyvista' not in sys.modules and 'vtk' not in sys.modules"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0
