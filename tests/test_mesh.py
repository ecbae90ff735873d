"""Mesh generators, surfaces, quality, files and validation, each checked against something
independent of the code under test (closed-form counts and volumes, the divergence theorem,
textbook angles, hand-written files)."""

import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

from tissue.errors import TissueError
from tissue.mesh import (PvdSeries, aspect_ratios, beam, boundary_faces, boundary_surface, box,
                         is_watertight_oriented, min_dihedral_angles, read_mesh, summary, write_vtu)

REGULAR_TET = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], dtype=float)
UNIT_TET = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)


def det_volumes(points, tets):
    """Signed volumes by a 4x4 determinant, independently of TetMesh's formula."""
    homogeneous = np.concatenate([points[tets], np.ones((len(tets), 4, 1))], axis=2)
    return -np.linalg.det(homogeneous) / 6.0


def write_with_meshio(path, points, cells, **options):
    meshio.Mesh(np.asarray(points, dtype=float), cells).write(path, **options)
    return path


# --- generators -------------------------------------------------------------------------------

def test_box_counts_volume_orientation():
    nx, ny, nz = 3, 4, 5
    mesh = box(size=(1.5, 2.0, 0.5), cells=(nx, ny, nz), origin=(1.0, -2.0, 3.0))
    assert mesh.n_points == (nx + 1) * (ny + 1) * (nz + 1)
    assert mesh.n_tets == 6 * nx * ny * nz
    vol = det_volumes(mesh.points, mesh.tets)
    assert np.all(vol > 0)
    assert vol.sum() == pytest.approx(1.5 * 2.0 * 0.5)
    np.testing.assert_allclose(mesh.bounds()[0], [1.0, -2.0, 3.0])
    np.testing.assert_allclose(mesh.bounds()[1], [2.5, 0.0, 3.5])
    # Conforming: no face is shared by more than two tets, every interior face by exactly two.
    faces = np.sort(mesh.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2


def test_sofa_reference_beam_counts():
    mesh = box(size=(1.0, 1.0, 4.6), cells=(20, 20, 92))
    assert (mesh.n_points, mesh.n_tets) == (41013, 220800)
    spacing = np.unique(np.round(mesh.points[:, 2], 9))
    np.testing.assert_allclose(np.diff(spacing), 0.05)


def test_beam_is_along_x_centred_section():
    mesh = beam(2.0, 0.4, 0.2, cells_along=10, cells_across=(4, 2))
    np.testing.assert_allclose(mesh.bounds()[0], [0.0, -0.2, -0.1])
    np.testing.assert_allclose(mesh.bounds()[1], [2.0, 0.2, 0.1])
    assert mesh.n_points == 11 * 5 * 3
    assert beam(1.0, 0.1, 0.1, 5, 2).n_tets == 6 * 5 * 2 * 2


def test_box_rejects_bad_cells():
    with pytest.raises(TissueError, match="cells"):
        box(cells=(0, 1, 1))


# --- surface ----------------------------------------------------------------------------------

def test_box_boundary_is_closed_outward_and_counted():
    nx, ny, nz = 3, 4, 5
    size = np.array([1.5, 2.0, 0.5])
    mesh = box(size=tuple(size), cells=(nx, ny, nz), origin=(-0.3, 0.2, 0.7))
    faces = boundary_faces(mesh.tets)
    assert len(faces) == 2 * (2 * nx * ny + 2 * ny * nz + 2 * nx * nz)
    assert is_watertight_oriented(faces)
    # Divergence theorem with F(x) = x: V = (1/3) sum over faces of centroid . (area normal).
    p = mesh.points[faces]
    area_normals = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.einsum("ij,ij->", p.mean(axis=1), area_normals) / 3.0 == pytest.approx(np.prod(size))
    # Every boundary vertex lies on a face of the box.
    lo, hi = mesh.bounds()
    ids, local = boundary_surface(mesh)
    on_face = np.isclose(mesh.points[ids], lo).any(1) | np.isclose(mesh.points[ids], hi).any(1)
    assert on_face.all()
    assert len(ids) == mesh.n_points - (nx - 1) * (ny - 1) * (nz - 1)
    np.testing.assert_array_equal(ids[local], faces)


def test_watertight_check_rejects_open_and_flipped_surfaces():
    faces = boundary_faces(np.array([[0, 1, 2, 3]]))
    assert is_watertight_oriented(faces)
    assert not is_watertight_oriented(faces[:3])
    flipped = faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert not is_watertight_oriented(flipped)


# --- quality ----------------------------------------------------------------------------------

def test_regular_tet_quality():
    tets = np.array([[0, 1, 2, 3]])
    assert det_volumes(REGULAR_TET, tets)[0] > 0
    assert min_dihedral_angles(REGULAR_TET, tets)[0] == pytest.approx(np.degrees(np.arccos(1 / 3)))
    assert aspect_ratios(REGULAR_TET, tets)[0] == pytest.approx(1.0)


def test_corner_tet_and_sliver_quality():
    tets = np.array([[0, 1, 2, 3]])
    # The corner tet has three right dihedral angles and three of arccos(1/sqrt(3)) = 54.74 degrees.
    assert min_dihedral_angles(UNIT_TET, tets)[0] == pytest.approx(np.degrees(np.arccos(1 / np.sqrt(3))))
    # A sliver: the four vertices of a square, two lifted slightly, volume near zero but no short edge.
    sliver = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.02], [0, 1, 0.02]], dtype=float)
    sliver_tet = np.array([[0, 1, 3, 2]]) if det_volumes(sliver, tets)[0] < 0 else tets
    assert min_dihedral_angles(sliver, sliver_tet)[0] < 5.0
    assert aspect_ratios(sliver, sliver_tet)[0] > 10.0


def test_summary_of_cube_grid():
    # Kuhn tetrahedra of cubes have dihedral angles 90, 60 and 45 degrees; 45 is the smallest.
    stats = summary(box(cells=(2, 2, 2)))
    assert stats["n_points"] == 27 and stats["n_tets"] == 48
    assert stats["volume"] == pytest.approx(1.0)
    assert stats["min_dihedral_deg"] == pytest.approx(45.0)
    assert stats["max_aspect_ratio"] > 1.0


# --- validation errors ------------------------------------------------------------------------

def test_missing_file_names_path(tmp_path):
    path = tmp_path / "nowhere" / "liver.vtu"
    with pytest.raises(TissueError, match="nowhere/liver.vtu: no such file"):
        read_mesh(path)


def test_unparseable_file_names_path(tmp_path):
    path = tmp_path / "junk.vtu"
    path.write_text("this is not a VTK file\n")
    with pytest.raises(TissueError, match="junk.vtu: cannot read") as info:
        read_mesh(path)
    assert "\n" not in str(info.value)


def test_non_finite_coordinates_name_the_point(tmp_path):
    points = UNIT_TET.copy()
    points[2, 1] = np.nan
    path = write_with_meshio(tmp_path / "nan.vtu", points, [("tetra", np.array([[0, 1, 2, 3]]))])
    with pytest.raises(TissueError, match=r"nan.vtu: non-finite coordinates at points 2"):
        read_mesh(path)


def test_index_out_of_range_names_the_tet(tmp_path):
    points = np.vstack([UNIT_TET, [1, 1, 1]])
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 7]])
    path = write_with_meshio(tmp_path / "range.vtu", points, [("tetra", tets)])
    with pytest.raises(TissueError, match=r"range.vtu: tetrahedra 1 index points out of range"):
        read_mesh(path)


def test_degenerate_tets_are_named(tmp_path):
    points = np.vstack([UNIT_TET, [0.5, 0.5, 0.0]])   # point 4 lies in the plane of 0, 1, 2
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [1, 2, 3, 3]])
    path = write_with_meshio(tmp_path / "flat.vtu", points, [("tetra", tets)])
    with pytest.raises(TissueError, match=r"flat.vtu: degenerate \(zero-volume\) tetrahedra 1, 2"):
        read_mesh(path)


@pytest.mark.parametrize("suffix", [".vtu", ".stl"])
def test_surface_only_file_asks_for_a_volume_mesh(tmp_path, suffix):
    faces = boundary_faces(np.array([[0, 1, 2, 3]]))
    options = {"binary": True} if suffix == ".stl" else {}
    path = write_with_meshio(tmp_path / f"skin{suffix}", UNIT_TET, [("triangle", faces)], **options)
    with pytest.raises(TissueError, match=rf"skin\{suffix}: contains only a surface \(triangles\); "
                                          r"a volume mesh \(tetrahedra\) is needed"):
        read_mesh(path)


def test_inverted_tet_is_reoriented_with_warning(tmp_path):
    path = write_with_meshio(tmp_path / "inside_out.vtu", UNIT_TET, [("tetra", np.array([[0, 2, 1, 3]]))])
    assert det_volumes(UNIT_TET, np.array([[0, 2, 1, 3]]))[0] < 0
    with pytest.warns(UserWarning, match="inside_out.vtu: re-oriented 1 inverted"):
        mesh = read_mesh(path)
    assert det_volumes(mesh.points, mesh.tets)[0] == pytest.approx(1 / 6)


# --- files ------------------------------------------------------------------------------------

def test_meshio_file_drops_unused_points_and_other_cells(tmp_path):
    # Points 0 and 2 are unused; the tet uses 1, 3, 4, 5; a triangle and a line are ignored.
    points = np.vstack([[9, 9, 9], UNIT_TET[0], [8, 8, 8], UNIT_TET[1:]])
    path = write_with_meshio(tmp_path / "mixed.vtu", points,
                             [("line", np.array([[0, 2]])), ("tetra", np.array([[1, 3, 4, 5]])),
                              ("triangle", np.array([[1, 3, 4]]))])
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.points, UNIT_TET)
    np.testing.assert_array_equal(mesh.tets, [[0, 1, 2, 3]])


def test_quadratic_tets_keep_their_corners(tmp_path):
    midpoints = UNIT_TET[[0, 1, 2, 0, 0, 1]] / 2 + UNIT_TET[[1, 2, 0, 3, 3, 3]] / 2
    path = write_with_meshio(tmp_path / "quadratic.vtu", np.vstack([UNIT_TET, midpoints]),
                             [("tetra10", np.arange(10)[None])])
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.points, UNIT_TET)
    np.testing.assert_array_equal(mesh.tets, [[0, 1, 2, 3]])


GMSH1_CUBE = """$NOD
9
10 0 0 0
20 1 0 0
30 1 1 0
40 0 1 0
50 0 0 1
60 1 0 1
70 1 1 1
80 0 1 1
999 5 5 5
$ENDNOD
$ELM
8
1 2 1 1 3 10 20 30
2 4 1 1 4 10 20 40 50
3 4 1 1 4 20 30 40 70
4 4 1 1 4 20 50 60 70
5 15 1 1 1 999
6 4 1 1 4 40 50 70 80
7 4 1 1 4 20 40 50 70
8 1 2 2 2 10 20
$ENDELM
"""


def test_gmsh1_legacy_cube(tmp_path):
    # A unit cube cut into 5 tets (4 corners + the middle one), labels 10..80 in steps of 10,
    # a label-999 point only used by a type-15 point element, plus a triangle and a line.
    path = tmp_path / "cube.msh"
    path.write_text(GMSH1_CUBE)
    mesh = read_mesh(path)
    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    np.testing.assert_array_equal(mesh.points, corners)
    assert mesh.n_tets == 5
    # Same vertex sets as the file's tets, with labels 10 k mapped to index k - 1.
    expected = np.array([[10, 20, 40, 50], [20, 30, 40, 70], [20, 50, 60, 70], [40, 50, 70, 80],
                         [20, 40, 50, 70]]) // 10 - 1
    np.testing.assert_array_equal(np.sort(mesh.tets, axis=1), np.sort(expected, axis=1))
    vol = det_volumes(mesh.points, mesh.tets)
    assert np.all(vol > 0) and vol.sum() == pytest.approx(1.0)


def test_gmsh1_undefined_label_is_named(tmp_path):
    path = tmp_path / "broken.msh"
    path.write_text(GMSH1_CUBE.replace("6 4 1 1 4 40 50 70 80", "6 4 1 1 4 40 50 70 81"))
    with pytest.raises(TissueError, match=r"broken.msh: tetrahedra use undefined node labels \[81\]"):
        read_mesh(path)


def test_vtu_round_trip(tmp_path):
    """Our VTU writer's file reads back through meshio's reader bit for bit, dtypes included (arrays
    of one compressed block and of several)."""
    mesh = box(size=(1.0, 2.0, 3.0), cells=(12, 13, 14))
    path = tmp_path / "out" / "box.vtu"
    rng = np.random.default_rng(0)
    point_data = {"u": rng.standard_normal(mesh.points.shape), "u_magnitude": rng.random(mesh.n_points),
                  "held": rng.integers(0, 2, mesh.n_points).astype(np.int32)}
    cell_data = {"volume": mesh.volumes, "f32": rng.random(mesh.n_tets).astype(np.float32)}
    write_vtu(path, mesh.points, mesh.tets, point_data=point_data, cell_data=cell_data)
    back = read_mesh(path)
    np.testing.assert_array_equal(back.points, mesh.points)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    raw = meshio.read(path)
    assert raw.points.tobytes() == mesh.points.tobytes()
    assert [block.type for block in raw.cells] == ["tetra"]
    np.testing.assert_array_equal(raw.cells[0].data, mesh.tets)      # meshio's reader makes them int64
    assert raw.point_data.keys() == point_data.keys() and raw.cell_data.keys() == cell_data.keys()
    for name, values in point_data.items():
        assert raw.point_data[name].dtype == values.dtype and raw.point_data[name].tobytes() == values.tobytes(), name
    for name, values in cell_data.items():
        assert raw.cell_data[name][0].dtype == values.dtype and raw.cell_data[name][0].tobytes() == values.tobytes()


def test_vtu_reads_in_vtk(tmp_path):
    """ParaView's reader (VTK's own) reads the same file: cells, points and data."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    mesh = box(cells=(10, 10, 10))
    u = np.random.default_rng(1).standard_normal(mesh.points.shape)
    write_vtu(tmp_path / "box.vtu", mesh.points, mesh.tets, point_data={"u": u}, cell_data={"volume": mesh.volumes})
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(tmp_path / "box.vtu"))
    reader.Update()
    grid = reader.GetOutput()
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetCells().GetConnectivityArray()).reshape(-1, 4), mesh.tets)
    assert {grid.GetCellType(i) for i in range(grid.GetNumberOfCells())} == {vtk.VTK_TETRA}
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetPoints().GetData()), mesh.points)
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetPointData().GetArray("u")), u)
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetCellData().GetArray("volume")), mesh.volumes)


def test_vtu_refuses_a_dtype_it_cannot_write(tmp_path):
    mesh = box(cells=(1, 1, 1))
    with pytest.raises(TissueError, match="flag: cannot write bool"):
        write_vtu(tmp_path / "bool.vtu", mesh.points, mesh.tets, point_data={"flag": np.ones(mesh.n_points, bool)})


def test_pvd_series(tmp_path):
    mesh = box(cells=(1, 1, 2))
    outside = tmp_path / "beam.pvd"
    outside.write_text("the user's own file")
    series = PvdSeries(tmp_path / "run", "beam")
    times = [0.0, 0.04, 0.08]
    for t in times:
        series.write(t, mesh.points + t, mesh.tets, point_data={"displacement": np.full_like(mesh.points, t)})
    assert outside.read_text() == "the user's own file"
    root = ET.parse(tmp_path / "run" / "beam.pvd").getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    datasets = root.findall("./Collection/DataSet")
    assert [float(d.get("timestep")) for d in datasets] == times
    assert [d.get("file") for d in datasets] == [f"beam_{i:06d}.vtu" for i in range(3)]
    for t, d in zip(times, datasets):
        step = meshio.read(tmp_path / "run" / d.get("file"))
        np.testing.assert_allclose(step.points, mesh.points + t)
        np.testing.assert_allclose(step.point_data["displacement"], t)
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["beam.pvd"] + [d.get("file") for d in datasets]
    with pytest.raises(TissueError, match="plain file name"):
        PvdSeries(tmp_path, "../escape")
