"""Reading tetrahedral meshes from files and writing results for ParaView.

meshio reads the modern formats (vtu, vtk, msh 2/4, medit, ...). The legacy Gmsh 1.0 format
(`$NOD` ... `$ENDNOD`, `$ELM` ... `$ENDELM`), still used by SOFA's example meshes, is read here
because meshio cannot. Every failure is a one-line TissueError that names the file.

The VTU files of a run are written here too, not by meshio: importing meshio (all its formats'
modules) is a noticeable part of `tissue run`'s start, and a tetrahedral VTU is a few lines of XML
around compressed base64 arrays. meshio is imported only to read a file.
"""

from __future__ import annotations

import base64
import os
import sys
import xml.etree.ElementTree as ET
import zlib
from contextlib import redirect_stderr, redirect_stdout
from io import StringIO
from pathlib import Path

import numpy as np

from ..errors import TissueError
from .tetmesh import TetMesh

# Cell types that make a file a surface rather than a volume (the common mistake: an .stl/.obj).
SURFACE_CELLS = {"triangle", "triangle6", "quad", "quad8", "quad9", "polygon"}
GMSH1_TETRAHEDRON = 4
VTK_TETRA = 10
VTU_BLOCK = 32768          # bytes of an array compressed apart (VTK's own default)
VTU_TYPES = {np.dtype(t): name for t, name in ((np.float64, "Float64"), (np.float32, "Float32"), (np.int64, "Int64"),
                                                (np.int32, "Int32"), (np.uint8, "UInt8"))}


def read_mesh(path) -> TetMesh:
    """The tetrahedra of a mesh file, with points no tetrahedron uses dropped.

    Other cells (boundary triangles, lines, ...) are ignored; quadratic tetrahedra (tetra10)
    keep their four corners.
    """
    path = Path(path)
    if not path.is_file():
        raise TissueError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    with open(path, "rb") as f:
        legacy = f.read(64).lstrip().startswith(b"$NOD")
    points, tets = _read_gmsh1(path) if legacy else _read_meshio(path)
    # Validate first on the file's own numbering, so that point ids in errors match the file.
    mesh = TetMesh(points, tets, source=str(path))
    used = np.unique(mesh.tets)
    if len(used) == mesh.n_points:
        return mesh
    return TetMesh(mesh.points[used], np.searchsorted(used, mesh.tets), source=str(path))


def _read_meshio(path: Path) -> tuple[np.ndarray, np.ndarray]:
    # meshio reports a file it cannot parse by printing the reason and calling sys.exit(1):
    # capture what it prints and turn both that and its exceptions into one TissueError.
    import meshio

    printed = StringIO()
    try:
        with redirect_stdout(printed), redirect_stderr(printed):
            mesh = meshio.read(path)
    except (Exception, SystemExit) as err:
        reason = printed.getvalue() if isinstance(err, SystemExit) else f"{type(err).__name__}: {err}"
        lines = [line.strip().removeprefix("Error: ") for line in reason.splitlines() if line.strip()]
        raise TissueError(f"{path}: cannot read as a mesh ({lines[0] if lines else 'unknown format'})") from None
    tets = [block.data[:, :4] for block in mesh.cells if block.type in ("tetra", "tetra10")]
    if tets:
        return mesh.points, np.concatenate(tets)
    kinds = sorted({block.type for block in mesh.cells})
    if kinds and set(kinds) <= SURFACE_CELLS:
        raise TissueError(f"{path}: contains only a surface ({', '.join(k + 's' for k in kinds)}); a volume "
                          "mesh (tetrahedra) is needed — tetrahedralise it first (e.g. gmsh -3, TetGen, fTetWild)")
    raise TissueError(f"{path}: contains no tetrahedra (cell types: {', '.join(kinds) or 'none'}); "
                      "a volume mesh (tetrahedra) is needed")


def _read_gmsh1(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Gmsh 1.0: node lines `label x y z`, element lines `id type phys elem n node-labels...`.

    Node labels are arbitrary integers; they are mapped to 0-based indices in file order.
    """
    tokens = path.read_text(errors="replace").split()

    def section(name: str) -> tuple[int, list[str]]:
        try:
            start, end = tokens.index(f"${name}"), tokens.index(f"$END{name}")
            return int(tokens[start + 1]), tokens[start + 2:end]
        except (ValueError, IndexError):
            raise TissueError(f"{path}: legacy Gmsh 1.0 file without a valid ${name} ... $END{name} section") from None

    n_nodes, nodes = section("NOD")
    if len(nodes) != 4 * n_nodes:
        raise TissueError(f"{path}: $NOD declares {n_nodes} nodes but holds {len(nodes) / 4:g} lines of 'label x y z'")
    n_elements, elements = section("ELM")
    tet_labels, i = [], 0
    try:
        for _ in range(n_elements):
            n_vertices = int(elements[i + 4])
            if int(elements[i + 1]) == GMSH1_TETRAHEDRON:
                tet_labels.append(elements[i + 5:i + 5 + n_vertices])
            i += 5 + n_vertices
        table = np.array(nodes, dtype=object).reshape(-1, 4)
        labels, points = table[:, 0].astype(np.int64), table[:, 1:].astype(np.float64)
        tet_labels = np.array(tet_labels, dtype=np.int64).reshape(len(tet_labels), 4)
    except (ValueError, IndexError):
        raise TissueError(f"{path}: malformed legacy Gmsh 1.0 file (bad number or truncated element list)") from None
    if i != len(elements):
        raise TissueError(f"{path}: $ELM declares {n_elements} elements but its data does not match that count")
    if not len(tet_labels):
        raise TissueError(f"{path}: contains no tetrahedra (element type 4); a volume mesh (tetrahedra) is needed")
    unique, counts = np.unique(labels, return_counts=True)
    if np.any(counts > 1):
        raise TissueError(f"{path}: node labels defined more than once: {unique[counts > 1][:10].tolist()}")
    undefined = np.setdiff1d(tet_labels, labels)
    if len(undefined):
        raise TissueError(f"{path}: tetrahedra use undefined node labels {undefined[:10].tolist()}")
    order = np.argsort(labels)
    return points, order[np.searchsorted(labels, tet_labels, sorter=order)]


def write_vtu(path, points, tets, point_data=None, cell_data=None) -> None:
    """One tetrahedral mesh as a VTK XML file (zlib-compressed base64 arrays); point_data / cell_data
    map names to per-point / per-tet arrays (float64, float32, int64, int32 or uint8)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    points, tets = np.asarray(points, dtype=np.float64), np.asarray(tets)
    n_points, n_tets = len(points), len(tets)
    cells = (("connectivity", tets.ravel()), ("offsets", np.arange(4, 4 * n_tets + 1, 4, dtype=tets.dtype)),
             ("types", np.full(n_tets, VTK_TETRA, dtype=np.uint8)))
    byte_order = "LittleEndian" if sys.byteorder == "little" else "BigEndian"
    parts = ['<?xml version="1.0"?>\n',
             f'<VTKFile type="UnstructuredGrid" version="0.1" byte_order="{byte_order}" header_type="UInt64" '
             'compressor="vtkZLibDataCompressor">\n',
             f'<UnstructuredGrid>\n<Piece NumberOfPoints="{n_points}" NumberOfCells="{n_tets}">\n<Points>\n',
             _data_array("Points", points), "</Points>\n<Cells>\n", *(_data_array(n, a) for n, a in cells), "</Cells>\n"]
    for section, data in (("PointData", point_data), ("CellData", cell_data)):
        if data:
            parts += [f"<{section}>\n", *(_data_array(name, values) for name, values in data.items()), f"</{section}>\n"]
    parts.append("</Piece>\n</UnstructuredGrid>\n</VTKFile>\n")
    path.write_text("".join(parts), encoding="ascii")


def _data_array(name: str, values) -> str:
    """A DataArray element: the array's bytes in this machine's order, compressed by zlib in blocks of
    VTU_BLOCK bytes (zlib's fastest level: about half the size), in base64 after
    the header VTK reads (UInt64: blocks, block size, last block's size, each block's compressed size)."""
    values = np.ascontiguousarray(values)
    try:
        kind = VTU_TYPES[values.dtype]
    except KeyError:
        raise TissueError(f"{name}: cannot write {values.dtype} to a VTU file") from None
    components = f' NumberOfComponents="{values.shape[1]}"' if values.ndim == 2 else ""
    data = values.tobytes()
    blocks = [zlib.compress(data[i:i + VTU_BLOCK], 1) for i in range(0, len(data), VTU_BLOCK)]
    last = len(data) - VTU_BLOCK * (len(blocks) - 1) if blocks else 0
    header = np.array([len(blocks), VTU_BLOCK, last, *map(len, blocks)], dtype=np.uint64)
    encoded = (base64.b64encode(header.tobytes()) + base64.b64encode(b"".join(blocks))).decode("ascii")
    return f'<DataArray type="{kind}" Name="{name}"{components} format="binary">\n{encoded}\n</DataArray>\n'


class PvdSeries:
    """A ParaView time series: `directory/name_000000.vtu`, ... listed in `directory/name.pvd`.

    Files are only ever written inside `directory` (created if missing); the .pvd is rewritten
    after every step, so a run stopped early still leaves a series ParaView can open.
    """

    def __init__(self, directory, name: str):
        if not name or Path(name).name != name or name in (".", ".."):
            raise TissueError(f"PvdSeries: name must be a plain file name without directories, got {name!r}")
        self.directory = Path(directory)
        self.name = name
        self.steps: list[tuple[float, str]] = []
        self.directory.mkdir(parents=True, exist_ok=True)

    @property
    def pvd_path(self) -> Path:
        return self.directory / f"{self.name}.pvd"

    def write(self, time: float, points, tets, point_data=None, cell_data=None) -> Path:
        """Write one step and update the .pvd; returns the step's .vtu path."""
        file = f"{self.name}_{len(self.steps):06d}.vtu"
        write_vtu(self.directory / file, points, tets, point_data, cell_data)
        self.steps.append((float(time), file))
        root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
        collection = ET.SubElement(root, "Collection")
        for t, f in self.steps:
            ET.SubElement(collection, "DataSet", timestep=repr(t), group="", part="0", file=f)
        ET.indent(root)
        # Write then rename, so ParaView never sees a half-written .pvd.
        partial = self.pvd_path.with_name(self.pvd_path.name + ".partial")
        ET.ElementTree(root).write(partial, encoding="utf-8", xml_declaration=True)
        os.replace(partial, self.pvd_path)
        return self.directory / file
