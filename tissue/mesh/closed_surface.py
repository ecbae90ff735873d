"""Closed triangle surfaces, the input of `tetrahedralize`: reading them from files (.obj, .stl,
.ply, .off), checking that they are closed and manifold, sampling them, and the geometry queries
the mesher asks of them (open3d's RaycastingScene: signed distance, ray hits, closest points).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import TissueError

SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off")


def surface_edges_report(triangles: np.ndarray) -> tuple[int, int, int]:
    """(boundary, non-manifold, badly oriented) edge counts of a triangle surface: edges used by
    one triangle, by more than two, and pairs traversed twice in the same direction."""
    tri = np.asarray(triangles, dtype=np.int64)
    directed = tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    boundary = int(np.sum(counts == 1))
    non_manifold = int(np.sum(counts > 2))
    # For manifold edges the two uses must have opposite directions: exactly one goes low -> high.
    forward = (directed[:, 0] < directed[:, 1]).astype(np.int64)
    n_forward = np.bincount(inverse, weights=forward, minlength=len(counts))
    misoriented = int(np.sum((counts == 2) & (n_forward != 1)))
    return boundary, non_manifold, misoriented


def enclosed_volume(points, triangles) -> float:
    """Signed volume enclosed by a closed triangle surface (divergence theorem): positive when the
    triangles are oriented with outward normals."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(triangles)]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def check_surface(points, triangles, source: str) -> tuple[np.ndarray, np.ndarray]:
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise TissueError(f"{source}: surface points must be an (n, 3) array with n >= 4, "
                          f"got shape {points.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) < 4:
        raise TissueError(f"{source}: surface triangles must be an (m, 3) array with m >= 4, "
                          f"got shape {triangles.shape}")
    if not np.isfinite(points).all():
        raise TissueError(f"{source}: the surface has non-finite coordinates")
    triangles = triangles.astype(np.int64)
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise TissueError(f"{source}: surface triangles index points out of range [0, {len(points)})")
    points, triangles = _merge_duplicate_points(points, triangles)
    degenerate = (triangles[:, 0] == triangles[:, 1]) | (triangles[:, 1] == triangles[:, 2]) | (
        triangles[:, 0] == triangles[:, 2])
    triangles = triangles[~degenerate]
    boundary, non_manifold, _ = surface_edges_report(triangles)
    if boundary:
        raise TissueError(f"{source}: the surface is not closed ({boundary} boundary edges); "
                          "a closed surface is needed to fill it with tetrahedra")
    if non_manifold:
        raise TissueError(f"{source}: the surface is not a manifold ({non_manifold} edges shared by "
                          "more than two triangles); a closed manifold surface is needed to fill it "
                          "with tetrahedra")
    return points, triangles


def _merge_duplicate_points(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge points with identical coordinates (STL stores each triangle's corners separately)."""
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    if len(unique) == len(points):
        return points, triangles
    return unique, inverse.ravel()[triangles]


def read_surface(path) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64, triangles (m, 3) int64) of a closed surface file: .obj, .stl, .ply
    or .off. Polygons are split into triangles and duplicated corners merged. Raises TissueError
    naming the path when the file is missing or unreadable, or the surface is not closed."""
    path = Path(path)
    if not path.is_file():
        raise TissueError(f"{path}: no such file")
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise TissueError(f"{path}: unknown surface format {path.suffix!r} (expected one of "
                          f"{', '.join(SURFACE_SUFFIXES)})")
    try:
        points, triangles = _read_meshio(path)
    except Exception as meshio_error:  # noqa: BLE001 - try open3d before giving up
        try:
            points, triangles = _read_open3d(path)
        except Exception:  # noqa: BLE001
            points, triangles = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        if len(triangles) == 0:
            raise TissueError(f"{path}: cannot read a triangle surface from it ({meshio_error})") from None
    if len(triangles) == 0:
        raise TissueError(f"{path}: the file holds no triangles")
    return check_surface(points, triangles, str(path))


def _read_meshio(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import meshio

    mesh = meshio.read(str(path))
    triangles = []
    for block in mesh.cells:
        data = np.asarray(block.data)
        if block.type == "triangle":
            triangles.append(data)
        elif (block.type == "quad" or block.type.startswith("polygon")) and data.ndim == 2:
            # Fan triangulation of each polygon.
            fan = [data[:, [0, i, i + 1]] for i in range(1, data.shape[1] - 1)]
            triangles.append(np.stack(fan, axis=1).reshape(-1, 3))
    if not triangles:
        raise ValueError("no triangles")
    return np.asarray(mesh.points, dtype=np.float64)[:, :3], np.concatenate(triangles).astype(np.int64)


def _read_open3d(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def surface_samples(points: np.ndarray, triangles: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` points spread over the surface in proportion to area (fixed seed), with the outward
    normal of the triangle each lies on."""
    p = points[triangles]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(0)
    tri = rng.choice(len(triangles), size=count, p=area / area.sum())
    a, b = rng.random(count), rng.random(count)
    flip = a + b > 1.0
    a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
    pts = p[tri, 0] + a[:, None] * (p[tri, 1] - p[tri, 0]) + b[:, None] * (p[tri, 2] - p[tri, 0])
    normals = cross[tri] / np.maximum(np.linalg.norm(cross[tri], axis=1, keepdims=True), 1e-300)
    return pts, normals


def open3d_core():
    """open3d's compiled core (`open3d.pybind`: core, t.geometry, io), loaded without the package's
    Python layer, whose visualisation imports dash, plotly and IPython: a fraction of the
    package's import time, paid by every run that meshes an organ. The module is registered under its own
    name, so a later `import open3d` adopts it rather than loading the extension twice; where the
    package is laid out otherwise (another open3d version), the package itself."""
    import importlib.machinery
    import importlib.util
    import os
    import sys

    if "open3d.pybind" in sys.modules:
        return sys.modules["open3d.pybind"]
    package = importlib.util.find_spec("open3d")
    if package is None:
        raise TissueError("open3d is not installed; the mesher needs it (pip install open3d)")
    spec = importlib.machinery.PathFinder.find_spec("open3d.pybind", package.submodule_search_locations)
    if spec is None or not isinstance(spec.loader, importlib.machinery.ExtensionFileLoader):
        import open3d

        return open3d
    os.environ["TCM_ENABLE"] = "1"          # as the package's __init__ sets before it loads the core
    module = importlib.util.module_from_spec(spec)
    sys.modules["open3d.pybind"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules["open3d.pybind"]
        raise
    return module


class SurfaceQueries:
    """Signed distance and closest points of a closed triangle surface (open3d, float32 inside)."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray):
        o3d = open3d_core()

        self._o3c = o3d.core
        self.offset = points.mean(axis=0)  # query near the origin: float32 keeps its precision
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor((points - self.offset).astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(triangles.astype(np.int32))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)

    def _query(self, x: np.ndarray):
        return self._o3c.Tensor(np.ascontiguousarray(x - self.offset, dtype=np.float32))

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        if len(x) == 0:
            return np.zeros(0)
        return self.scene.compute_signed_distance(self._query(x), nsamples=3).numpy().astype(np.float64)

    def first_hit(self, x: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Distance to the first crossing of the rays x + t direction (t > 0), inf if none."""
        if len(x) == 0:
            return np.zeros(0)
        rays = np.hstack([x - self.offset, direction]).astype(np.float32)
        return self.scene.cast_rays(self._o3c.Tensor(rays))["t_hit"].numpy().astype(np.float64)

    def closest(self, x: np.ndarray) -> np.ndarray:
        if len(x) == 0:
            return np.zeros((0, 3))
        found = self.scene.compute_closest_points(self._query(x))
        return found["points"].numpy().astype(np.float64) + self.offset
