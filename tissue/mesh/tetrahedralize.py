"""Fill a closed triangle surface with tetrahedra at a chosen resolution.

No patient mesh ships with `tissue`, so volume meshes are made here: from the procedural organs of
`tissue.mesh.organs`, or from any closed surface a user has (.obj, .stl, .ply, .off via
`read_surface`).

Method (vectorised numpy; open3d's RaycastingScene answers signed distance, ray and closest-point
queries):

1. Lattice. A body-centred-cubic (BCC) lattice of cube edge `spacing` covers the bounding box:
   cube corners and centres, four tetrahedra around each centre-to-centre edge (twelve per cube),
   all congruent with dihedral angles of 60 and 90 degrees.
2. Isosurface stuffing (Labelle & Shewchuk, SIGGRAPH 2007). The surface cuts lattice edges at
   points found by casting rays along them. A lattice vertex closer to a cut point than 0.25 (long
   edges) or 0.41 (short edges) of the edge is warped onto it. Tetrahedra inside are kept whole;
   those crossing the surface are cut into one to three tetrahedra at the cut points (stencils by
   the signs of their vertices). Quadrilaterals are split through their smallest global vertex id,
   which keeps neighbours conforming and every prism splittable; this is not the paper's parity
   rule, so its 10.7-degree bound is not claimed, but quality comes out better after step 3. Where
   parts thinner than the lattice touch at a warped vertex (a pinch in the boundary), that vertex is
   left unwarped and the stuffing repeated, which resolves it as marching tetrahedra would, to a
   manifold. Specks (components under 2 % of the largest one's volume) are dropped.
3. Optimisation. Every boundary vertex lies on the surface after stuffing and stays there: the
   boundary is spread over the surface by centroidal-Voronoi steps on surface samples (reaching
   into rims the lattice under-samples), the boundary is smoothed along the surface and the
   interior toward its neighbours, and the vertices of the worst tetrahedra move toward the apex
   that would make them regular. Every move is guarded by the smallest dihedral angle of the
   tetrahedra around the vertex (no inversion; a move is kept only if it raises that angle, or
   for spreading if it stays above 15 degrees), retried at smaller steps. A tetrahedron with all
   four vertices on the boundary and an angle under 10 degrees is dropped.

`target_tets` is reached by secant steps on the spacing (count ~ 12 volume / spacing^3) and a few
lattice shifts: the result lands within a few per cent of the target.

Achieved (tests/test_organs.py): minimum dihedral angle >= 14 degrees on every surface tried --
the procedural liver, stomach and colon, spheres, a box, a torus, a thin plate, from 1,000 to
20,000 tetrahedra (liver at 1,300 / 1,600 / 3,900 target: 25.0 / 22.6 / 19.6 degrees); the tests
assert >= 12. Boundary vertices lie on the surface to float32 precision (~1e-6 of the spacing).
Parts thinner than the spacing are lost or serrated, and sharp edges and corners of the input are
rounded off at the scale of the spacing (stuffing does not keep features): the liver at 1,300
tetrahedra holds 94 % of the volume its surface encloses, 97.5 % at 3,900 and 99 % at 20,000. About 0.4 s for 1,300
tetrahedra and 2 s for 20,000 on one core (after open3d's import).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import TissueError
from .tetmesh import TetMesh, signed_volumes

# The four faces of a positively oriented tetrahedron, each ordered so its normal points outward.
_OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# The faces (rows of _OUTWARD_FACES) meeting at each edge of _EDGES: the faces opposite the two
# vertices not on the edge.
_EDGE_FACES = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])

SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off")

# Dihedral angles (degrees): the optimisation's spreading of the boundary over the surface keeps
# every angle above _SPREAD_FLOOR (or where it was, if lower); a tetrahedron with all four vertices
# on the boundary and an angle under _DROP_BELOW is dropped rather than kept.
_SPREAD_FLOOR = 15.0
_DROP_BELOW = 10.0
# Lattices beyond this many tetrahedra (memory of the order of 10 GB) are refused.
_MAX_LATTICE_TETS = 30_000_000


# --------------------------------------------------------------------------------------------
# Closed surfaces


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


def _check_surface(points, triangles, source: str) -> tuple[np.ndarray, np.ndarray]:
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
    return _check_surface(points, triangles, str(path))


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


# --------------------------------------------------------------------------------------------
# Geometry queries


class _Surface:
    """Signed distance and closest points of a closed triangle surface (open3d, float32 inside)."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray):
        import open3d as o3d

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


# --------------------------------------------------------------------------------------------
# Lattice


def _bcc_lattice(lo: np.ndarray, hi: np.ndarray, h: float,
                 shift=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Points and positively oriented tetrahedra of a BCC lattice of cube edge h covering [lo, hi]
    with at least one cube of margin."""
    n = np.ceil((hi - lo) / h).astype(np.int64) + 3  # cubes per axis
    origin = 0.5 * (lo + hi) - 0.5 * h * n + h * np.asarray(shift, dtype=np.float64)
    nx, ny, nz = (int(v) for v in n)
    corner = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    centre = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1)
    points = np.concatenate([corner.reshape(-1, 3) * h, (centre.reshape(-1, 3) + 0.5) * h]) + origin
    n_corner = (nx + 1) * (ny + 1) * (nz + 1)

    def corner_id(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    def centre_id(i, j, k):
        return n_corner + (i * ny + j) * nz + k

    tets = []
    for axis in range(3):
        # Pairs of cubes adjacent along `axis`: the cube at index c and the one at c + e_axis.
        shape = [nx, ny, nz]
        shape[axis] -= 1
        idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
        e = np.zeros(3, dtype=np.int64)
        e[axis] = 1
        a = centre_id(*idx.T)
        b = centre_id(*(idx + e).T)
        # The square face between them lies at corner index c + e_axis; u, v span it.
        u = np.zeros(3, dtype=np.int64)
        v = np.zeros(3, dtype=np.int64)
        u[(axis + 1) % 3] = 1
        v[(axis + 2) % 3] = 1
        base = idx + e
        square = [base, base + u, base + u + v, base + v]
        for s in range(4):
            p = corner_id(*square[s].T)
            q = corner_id(*square[(s + 1) % 4].T)
            tets.append(np.stack([a, b, p, q], axis=1))
    tets = np.concatenate(tets)
    flip = signed_volumes(points, tets) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return points, tets


# --------------------------------------------------------------------------------------------
# Mesh bookkeeping


def _group_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group equal rows of a sorted-within-row integer array: (order, group_start) such that
    rows[order[group_start[g]:group_start[g + 1]]] are the members of group g."""
    rows = rows.astype(np.int64)
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    n = int(rows.max()) + 1
    if n ** rows.shape[1] < 2 ** 62:
        key = rows[:, 0]
        for j in range(1, rows.shape[1]):
            key = key * n + rows[:, j]
        order = np.argsort(key, kind="stable")
        k = key[order]
        new = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    else:  # pragma: no cover - only for lattices of more than a million points
        order = np.lexsort(rows.T[::-1])
        r = rows[order]
        new = np.flatnonzero(np.r_[True, np.any(r[1:] != r[:-1], axis=1)])
    return order, np.r_[new, len(rows)]


def _faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary faces (k, 3), oriented outward, and the tetrahedron each belongs to."""
    faces = tets[:, _OUTWARD_FACES].reshape(-1, 3)
    order, start = _group_rows(np.sort(faces, axis=1))
    single = order[start[:-1][np.diff(start) == 1]]
    single.sort()
    return faces[single], single // 4


def _incidence(tets: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR vertex -> tetrahedra: tetrahedra of vertex v are tet_of[start[v]:start[v + 1]]."""
    flat = tets.ravel()
    order = np.argsort(flat, kind="stable")
    start = np.zeros(n_points + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=n_points), out=start[1:])
    return start, order // 4


def _unique_edges(cells: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    e = np.sort(cells[:, pairs].reshape(-1, 2), axis=1)
    order, start = _group_rows(e)
    return e[order[start[:-1]]]


def _quality(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Minimum dihedral angle in degrees; for inverted tetrahedra that angle minus 180 (< 0)."""
    p = points[tets[:, _OUTWARD_FACES]]
    n = np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    cos = -np.einsum("mij,mij->mi", n[:, _EDGE_FACES[:, 0]], n[:, _EDGE_FACES[:, 1]])
    angle = np.degrees(np.arccos(np.clip(cos.max(axis=1), -1.0, 1.0)))
    return np.where(signed_volumes(points, tets) > 0, angle, angle - 180.0)


def _nonmanifold_vertices(faces: np.ndarray, n_points: int) -> np.ndarray:
    """Vertices where a closed triangle surface is not a manifold: an edge there is shared by
    more than two triangles, or the triangles around the vertex form more than one fan."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    k = len(faces)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    # Edge uses: use 3f + j is the edge from corner j to corner j + 1 of face f.
    ends = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    order, start = _group_rows(np.sort(ends, axis=1))
    size = np.diff(start)
    bad = [np.unique(ends[order[start[:-1][size > 2]]])]
    first, second = order[start[:-1][size == 2]], order[start[:-1][size == 2] + 1]
    # Link the corners of the two faces that hold the same vertex (incidence id = 3f + corner).
    f1, j1 = first // 3, first % 3
    f2, j2 = second // 3, second % 3
    same = faces[f1, j1] == faces[f2, j2]
    a0, a1 = 3 * f1 + j1, 3 * f1 + (j1 + 1) % 3
    b0, b1 = 3 * f2 + j2, 3 * f2 + (j2 + 1) % 3
    rows = np.concatenate([a0, a1])
    cols = np.concatenate([np.where(same, b0, b1), np.where(same, b1, b0)])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * k, 3 * k))
    _, label = connected_components(graph, directed=False)
    vertex = faces.ravel()
    order, start = _group_rows(np.stack([vertex, label], axis=1))
    fans = np.bincount(vertex[order[start[:-1]]], minlength=n_points)
    bad.append(np.flatnonzero(fans > 1))
    return np.unique(np.concatenate(bad))


def _tet_components(tets: np.ndarray) -> np.ndarray:
    """Component label of each tetrahedron (connected through shared faces)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    order, start = _group_rows(np.sort(tets[:, _OUTWARD_FACES].reshape(-1, 3), axis=1))
    pairs = start[:-1][np.diff(start) == 2]
    a, b = order[pairs] // 4, order[pairs + 1] // 4
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(tets), len(tets)))
    return connected_components(graph, directed=False)[1]


def _compact(x: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inverse = np.unique(tets.ravel(), return_inverse=True)
    return x[used], inverse.reshape(tets.shape)


class _Topology:
    """What the optimisation needs to know about the connectivity, computed once per change."""

    def __init__(self, tets: np.ndarray, n: int):
        self.tets = tets
        self.faces, _ = _faces(tets)
        self.on_boundary = np.zeros(n, dtype=bool)
        self.on_boundary[self.faces.ravel()] = True
        self.boundary = np.flatnonzero(self.on_boundary)
        self.start, self.tet_of = _incidence(tets, n)
        self.interior = np.flatnonzero(~self.on_boundary & (np.diff(self.start) > 0))
        self.edges = _unique_edges(tets, _EDGES)
        self.boundary_edges = _unique_edges(self.faces, np.array([[0, 1], [1, 2], [2, 0]]))
        self.all_boundary = np.flatnonzero(self.on_boundary[tets].all(axis=1))

    def star(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tetrahedra around `vertices`, concatenated; segment starts, one per vertex)."""
        counts = self.start[vertices + 1] - self.start[vertices]
        seg = np.cumsum(counts) - counts
        idx = np.repeat(self.start[vertices] - seg, counts) + np.arange(counts.sum())
        return self.tet_of[idx], seg

    def vertex_normals(self, x: np.ndarray) -> np.ndarray:
        f = x[self.faces]
        fn = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
        vn = np.zeros_like(x)
        for c in range(3):
            np.add.at(vn, self.faces[:, c], fn)
        return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _guarded_move(x, q, topo: _Topology, movers, proposed, floor) -> tuple[np.ndarray, np.ndarray]:
    """Move `movers` to `proposed` together, then undo moves until every moved vertex has all its
    tetrahedra at quality >= its floor. Returns the new (x, q)."""
    if len(movers) == 0:
        return x, q
    tets = topo.tets
    star, seg = topo.star(movers)
    x_new = x.copy()
    x_new[movers] = proposed
    q_new = q.copy()
    changed = np.unique(star)
    moving = np.ones(len(movers), dtype=bool)
    for _ in range(100):
        q_new[changed] = _quality(x_new, tets[changed])
        fail = moving & (np.minimum.reduceat(q_new[star], seg) < floor)
        if not fail.any():
            break
        moving &= ~fail
        back = movers[fail]
        x_new[back] = x[back]
        changed = np.unique(topo.star(back)[0])
    else:  # pragma: no cover - the moved set shrinks every round, so this is not reached
        x_new[movers[moving]] = x[movers[moving]]
        q_new[:] = q
    return x_new, q_new


def _vertex_min(q, topo: _Topology, vertices: np.ndarray) -> np.ndarray:
    star, seg = topo.star(vertices)
    return np.minimum.reduceat(q[star], seg)


def _improve_worst(x, q, topo: "_Topology", surface, below: float = 25.0):
    """For each vertex of a tetrahedron under `below` degrees, try moving it toward the apex over
    the opposite face of its worst tetrahedron that would make that tetrahedron regular (boundary
    vertices then back onto the surface); keep the moves that raise the vertex's worst angle."""
    tets = topo.tets
    poor = np.flatnonzero(q < below)
    if len(poor) == 0:
        return x, q
    verts = np.unique(tets[poor])
    star, seg = topo.star(verts)
    # The worst tetrahedron around each vertex, and the vertex's corner in it.
    qs = q[star]
    vmin = np.minimum.reduceat(qs, seg)
    is_min = qs == np.repeat(vmin, np.diff(np.r_[seg, len(star)]))
    first = np.maximum.reduceat(np.where(is_min, np.arange(len(star)), -1), seg)
    worst = tets[star[first]]
    corner = np.argmax(worst == verts[:, None], axis=1)
    face = worst[np.arange(len(verts))[:, None], _OUTWARD_FACES[corner]]
    f = x[face]
    normal = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    edge = np.mean([np.linalg.norm(f[:, i] - f[:, j], axis=1) for i, j in ((0, 1), (1, 2), (2, 0))], axis=0)
    # The outward normal of the face points away from the vertex: the apex lies against it.
    apex = f.mean(axis=1) - normal * (np.sqrt(2.0 / 3.0) * edge)[:, None]
    boundary = topo.on_boundary[verts]
    for step in (0.5, 0.2):
        proposed = x[verts] + step * (apex - x[verts])
        if boundary.any():
            proposed[boundary] = surface.closest(proposed[boundary])
        x, q = _guarded_move(x, q, topo, verts, proposed, _vertex_min(q, topo, verts) + 1e-9)
    return x, q


def _neighbour_mean(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    n = len(x)
    deg = np.bincount(edges.ravel(), minlength=n).astype(np.float64)
    s = np.empty((n, 3))
    for d in range(3):
        s[:, d] = np.bincount(edges[:, 0], weights=x[edges[:, 1], d], minlength=n) + np.bincount(
            edges[:, 1], weights=x[edges[:, 0], d], minlength=n)
    return s / np.maximum(deg, 1.0)[:, None]


# --------------------------------------------------------------------------------------------
# Isosurface stuffing


# Isosurface stuffing (Labelle & Shewchuk 2007): a lattice vertex closer to a cut point than
# this fraction of the edge's length is warped onto it; long (axis-parallel, length h) and short
# (centre-to-corner, 0.87 h) edges of the BCC lattice.
_ALPHA_LONG = 0.24999
_ALPHA_SHORT = 0.41189

# Prism symmetries bringing vertex k to position 0 (prism (0,1,2)-(3,4,5), edges i - i+3).
_PRISM_ROTATIONS = np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4],
                             [3, 5, 4, 0, 2, 1], [4, 3, 5, 1, 0, 2], [5, 4, 3, 2, 1, 0]])


def _split_prisms(v: np.ndarray) -> np.ndarray:
    """Three tetrahedra for each prism (v0, v1, v2)-(v3, v4, v5), each quadrilateral face split by
    the diagonal through its smallest global id, so neighbours agree (Dompierre et al. 1999)."""
    v = v[np.arange(len(v))[:, None], _PRISM_ROTATIONS[np.argmin(v, axis=1)]]
    a = np.minimum(v[:, 1], v[:, 5]) < np.minimum(v[:, 2], v[:, 4])
    first = np.where(a[:, None], v[:, [0, 1, 2, 5]], v[:, [0, 1, 2, 4]])
    second = np.where(a[:, None], v[:, [0, 1, 5, 4]], v[:, [0, 4, 2, 5]])
    third = v[:, [0, 4, 5, 3]]
    return np.concatenate([first, second, third])


def _stuff(surface: "_Surface", lo, hi, h: float, shift=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Isosurface stuffing (see _stuff_lattice), repeated without warping the lattice vertices
    where the result's boundary pinches (two parts touching at a warped vertex, where the shape is
    thinner than the lattice): unwarped, they resolve as in marching tetrahedra, a manifold."""
    points, tets = _bcc_lattice(lo, hi, h, shift)
    sd = surface.signed_distance(points)
    tets = tets[sd[tets].min(axis=1) < 0.0]  # only tetrahedra inside or crossing matter
    if len(tets) == 0:
        return points[:0], np.zeros((0, 4), dtype=np.int64)
    no_warp = np.zeros(len(points), dtype=bool)
    for _ in range(6):
        x, result = _stuff_lattice(surface, points, tets, sd, h, no_warp)
        faces, _ = _faces(result) if len(result) else (np.zeros((0, 3), dtype=np.int64), None)
        pinched = _nonmanifold_vertices(faces, len(x))
        pinched = pinched[pinched < len(points)]  # lattice vertices (cut points come after)
        pinched = pinched[~no_warp[pinched]]
        if len(pinched) == 0:
            break
        no_warp[pinched] = True
    if len(result) == 0:
        return x[:0], result
    return _compact(x, result)


def _stuff_lattice(surface: "_Surface", points, tets, sd, h: float, no_warp) -> tuple[np.ndarray, np.ndarray]:
    """Isosurface stuffing on a BCC lattice: warp lattice vertices near the surface onto it, keep
    the tetrahedra inside, and cut those crossing the surface at their edges' cut points. The
    boundary of the result is a triangulation of points on the surface. Quadrilaterals are split
    by a global vertex order (not the paper's parity rule), so the angle bound of the paper does
    not hold as such; the optimisation afterwards repairs the few poor tetrahedra."""
    n = len(points)

    # Cut points: where the surface crosses edges with a vertex strictly inside and one outside.
    edges = _unique_edges(tets, _EDGES)
    a, b = edges[:, 0], edges[:, 1]
    crossing = (sd[a] < 0) != (sd[b] < 0)
    crossing &= (sd[a] != 0) & (sd[b] != 0)
    edges = edges[crossing]
    inner = np.where(sd[edges[:, 0]] < 0, edges[:, 0], edges[:, 1])
    outer = np.where(sd[edges[:, 0]] < 0, edges[:, 1], edges[:, 0])
    length = np.linalg.norm(points[outer] - points[inner], axis=1)
    direction = (points[outer] - points[inner]) / length[:, None]
    t = surface.first_hit(points[inner], direction)
    fallback = ~(t <= length)
    t[fallback] = (length * -sd[inner] / (sd[outer] - sd[inner]))[fallback]
    cut = points[inner] + t[:, None] * direction
    # Warp each vertex violated by a cut point (nearer than alpha of the edge) onto the nearest one.
    alpha = np.where(length > 0.95 * h, _ALPHA_LONG, _ALPHA_SHORT) * length
    dist = np.concatenate([t, length - t])
    vertex = np.concatenate([inner, outer])
    violated = (dist < np.concatenate([alpha, alpha])) & ~no_warp[vertex]
    order = np.lexsort((dist[violated], vertex[violated]))
    vv, cv = vertex[violated][order], np.concatenate([cut, cut])[violated][order]
    first = np.ones(len(vv), dtype=bool)
    first[1:] = vv[1:] != vv[:-1]
    warped = vv[first]
    points = points.copy()
    points[warped] = cv[first]
    sign = np.sign(sd).astype(np.int64)
    sign[warped] = 0

    # Cut points that survive: edges whose endpoints still have strictly opposite signs.
    alive = (sign[edges[:, 0]] * sign[edges[:, 1]]) < 0
    edges, cut = edges[alive], cut[alive]
    edge_key = np.sort(edges, axis=1)
    edge_key = edge_key[:, 0] * n + edge_key[:, 1]
    key_order = np.argsort(edge_key)
    edge_key = edge_key[key_order]
    cut_id = n + key_order  # global id of the cut point on each (sorted) edge

    def cut_of(p, q):
        k = np.minimum(p, q) * n + np.maximum(p, q)
        return cut_id[np.searchsorted(edge_key, k)]

    # Classify tetrahedra and order each one's vertices: inside first, then on, then outside.
    s = sign[tets]
    n_in, n_on, n_out = (s < 0).sum(1), (s == 0).sum(1), (s > 0).sum(1)
    rank = np.argsort(s, axis=1, kind="stable")
    v = np.take_along_axis(tets, rank, axis=1)
    out = []
    whole = (n_in > 0) & (n_out == 0)
    out.append(tets[whole])
    all_on = n_on == 4
    if all_on.any():
        inside = surface.signed_distance(points[tets[all_on]].mean(axis=1)) < 0
        out.append(tets[all_on][inside])
    sel = (n_in == 1) & (n_out == 3)
    w = v[sel]
    out.append(np.stack([w[:, 0], cut_of(w[:, 0], w[:, 1]), cut_of(w[:, 0], w[:, 2]),
                         cut_of(w[:, 0], w[:, 3])], 1))
    sel = (n_in == 1) & (n_on == 1) & (n_out == 2)
    w = v[sel]
    out.append(np.stack([w[:, 0], w[:, 1], cut_of(w[:, 0], w[:, 2]), cut_of(w[:, 0], w[:, 3])], 1))
    sel = (n_in == 1) & (n_on == 2) & (n_out == 1)
    w = v[sel]
    out.append(np.stack([w[:, 0], w[:, 1], w[:, 2], cut_of(w[:, 0], w[:, 3])], 1))
    sel = (n_in == 2) & (n_out == 2)
    w = v[sel]
    out.append(_split_prisms(np.stack([w[:, 0], cut_of(w[:, 0], w[:, 2]), cut_of(w[:, 0], w[:, 3]),
                                       w[:, 1], cut_of(w[:, 1], w[:, 2]), cut_of(w[:, 1], w[:, 3])], 1)))
    sel = (n_in == 3) & (n_out == 1)
    w = v[sel]
    out.append(_split_prisms(np.stack([w[:, 0], w[:, 1], w[:, 2], cut_of(w[:, 0], w[:, 3]),
                                       cut_of(w[:, 1], w[:, 3]), cut_of(w[:, 2], w[:, 3])], 1)))
    sel = (n_in == 2) & (n_on == 1) & (n_out == 1)
    w = v[sel]
    # A pyramid: apex the on vertex, base (i1, i2, c2, c1) split through its smallest id.
    i1, i2, z = w[:, 0], w[:, 1], w[:, 2]
    c1, c2 = cut_of(i1, w[:, 3]), cut_of(i2, w[:, 3])
    diag = np.minimum(i1, c2) < np.minimum(i2, c1)
    out.append(np.where(diag[:, None], np.stack([z, i1, i2, c2], 1), np.stack([z, i1, i2, c1], 1)))
    out.append(np.where(diag[:, None], np.stack([z, i1, c2, c1], 1), np.stack([z, i2, c2, c1], 1)))

    result = np.concatenate(out).astype(np.int64)
    all_points = np.concatenate([points, cut[key_order]]) if len(cut) else points
    vol = signed_volumes(all_points, result)
    flip = vol < 0
    result[flip, 2], result[flip, 3] = result[flip, 3].copy(), result[flip, 2].copy()
    # Tetrahedra flattened by warping (all four vertices on a locally flat surface) are dropped.
    edge_vec = all_points[result[:, [1, 2, 3, 2, 3, 3]]] - all_points[result[:, [0, 0, 0, 1, 1, 2]]]
    longest = np.sqrt((edge_vec ** 2).sum(-1).max(axis=1))
    return all_points, result[np.abs(vol) > 1e-6 * longest ** 3]


# --------------------------------------------------------------------------------------------
# Stages


def _surface_samples(points: np.ndarray, triangles: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
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


def _lloyd_targets(x: np.ndarray, topo: _Topology, samples, sample_normals) -> np.ndarray:
    """Centroid of the surface samples nearest to each boundary vertex among those facing the
    same way: a centroidal-Voronoi step that spreads the boundary over the whole surface, thin
    rims included. Vertices without samples keep their place."""
    from scipy.spatial import cKDTree

    b = topo.boundary
    normals = topo.vertex_normals(x)[b]
    k = min(6, len(b))
    _, near = cKDTree(x[b]).query(samples, k=k)
    near = near.reshape(len(samples), k)
    facing = np.einsum("skd,sd->sk", normals[near], sample_normals) > 0.2
    choice = np.where(facing.any(axis=1), facing.argmax(axis=1), 0)
    owner = near[np.arange(len(samples)), choice]
    count = np.bincount(owner, minlength=len(b)).astype(np.float64)
    target = x[b].copy()
    has = count > 0
    for d in range(3):
        target[has, d] = np.bincount(owner, weights=samples[:, d], minlength=len(b))[has] / count[has]
    return target


def _carve_nonmanifold(tets: np.ndarray, n: int) -> np.ndarray:
    """Remove tetrahedra at boundary vertices that joined parts at a point or an edge."""
    for _ in range(20):
        faces, _ = _faces(tets)
        bad = _nonmanifold_vertices(faces, n)
        if len(bad) == 0:
            return tets
        hit = np.isin(tets, bad).any(axis=1)
        label = _tet_components(tets)
        sizes = np.bincount(label)
        small = hit & (sizes[label] < sizes.max())
        tets = tets[~(small if small.any() else hit)]
    return tets


def _drop_specks(tets: np.ndarray, vol: np.ndarray, fraction: float = 0.02) -> np.ndarray:
    label = _tet_components(tets)
    comp_vol = np.bincount(label, weights=vol)
    return comp_vol[label] >= fraction * comp_vol.max()


def _optimise(x: np.ndarray, tets: np.ndarray, surface: "_Surface", samples, sample_normals,
              rounds: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Spread the boundary over the surface and smooth, all under quality guards; boundary
    vertices move only to points of the surface. Tetrahedra with four vertices on the boundary
    and a dihedral angle under _DROP_BELOW are dropped."""
    topo = None
    for _ in range(rounds):
        if topo is None:
            topo = _Topology(tets, len(x))
            q = _quality(x, tets)
            poor = topo.all_boundary[q[topo.all_boundary] < _DROP_BELOW]
            if 0 < len(poor) < len(tets):
                keep = np.ones(len(tets), dtype=bool)
                keep[poor] = False
                x, tets = _compact(x, _carve_nonmanifold(tets[keep], len(x)))
                topo = None
                continue
        b = topo.boundary
        x, q = _snap(x, q, topo, surface)
        # 1. Spread the boundary over the surface (a centroidal Voronoi step): it reaches into
        #    thin rims the lattice missed. Accepted where no angle falls under the spread floor.
        proposed = surface.closest(_lloyd_targets(x, topo, samples, sample_normals))
        x, q = _guarded_move(x, q, topo, b, proposed, np.minimum(_vertex_min(q, topo, b), _SPREAD_FLOOR))
        # 2. Smooth the boundary along the surface and the interior toward the neighbours' mean,
        #    where the worst angle around the vertex gets better.
        mean = _neighbour_mean(x, topo.boundary_edges)
        proposed = surface.closest(0.5 * (x[b] + mean[b]))
        x, q = _guarded_move(x, q, topo, b, proposed, _vertex_min(q, topo, b) + 1e-9)
        if len(topo.interior):
            i = topo.interior
            mean = _neighbour_mean(x, topo.edges)
            x, q = _guarded_move(x, q, topo, i, mean[i], _vertex_min(q, topo, i) + 1e-9)
        # 3. Move the vertices of the worst tetrahedra toward the apex that would make them regular.
        x, q = _improve_worst(x, q, topo, surface)
    for _ in range(3):
        topo = _Topology(tets, len(x))
        q = _quality(x, tets)
        poor = topo.all_boundary[q[topo.all_boundary] < _DROP_BELOW]
        if len(poor) == 0 or len(poor) == len(tets):
            break
        keep = np.ones(len(tets), dtype=bool)
        keep[poor] = False
        x, tets = _compact(x, _carve_nonmanifold(tets[keep], len(x)))
    topo = _Topology(tets, len(x))
    x, _ = _snap(x, _quality(x, tets), topo, surface)
    return _compact(x, tets)


def _snap(x, q, topo: "_Topology", surface, floor: float = 10.0):
    """Move boundary vertices that are off the surface (exposed by a removal) onto it: full step,
    else half, else a quarter, where no angle falls under `floor` (or where it was, if lower)."""
    b = topo.boundary
    for fraction in (1.0, 0.5, 0.25):
        target = surface.closest(x[b])
        off = np.linalg.norm(target - x[b], axis=1) > 1e-9 * (1.0 + np.abs(x[b]).max())
        if not off.any():
            break
        movers = b[off]
        floors = np.minimum(_vertex_min(q, topo, movers), floor)
        x, q = _guarded_move(x, q, topo, movers, x[movers] + fraction * (target[off] - x[movers]), floors)
    return x, q


def _mesh_at_spacing(surface: "_Surface", lo, hi, h: float, shift=(0.0, 0.0, 0.0), samples=None):
    """The stuffed tetrahedra at lattice spacing h; with samples, cleaned and optimised."""
    x, tets = _stuff(surface, lo, hi, h, shift)
    if samples is None or len(tets) == 0:
        return x, tets
    tets = _carve_nonmanifold(tets, len(x))
    if len(tets) == 0:
        return x[:0], tets
    tets = tets[_drop_specks(tets, signed_volumes(x, tets))]
    x, tets = _compact(x, tets)
    return _optimise(x, tets, surface, *samples)


def tetrahedralize(surface_points, surface_triangles, target_tets: int | None = None,
                   spacing: float | None = None, source: str = "surface") -> TetMesh:
    """Fill a closed triangle surface (points (n, 3), triangles (m, 3)) with tetrahedra.

    Give either `target_tets` (the result lands within a few per cent of it, for targets of a
    few hundred and more) or `spacing` (the edge of the BCC lattice's cubes, in the surface's
    units; the tetrahedra's edges are about that long); with neither, the target is 2,000. The
    surface must be closed and manifold; its orientation does not matter. The boundary vertices
    of the result lie on the surface and its minimum dihedral angle was >= 14 degrees on every
    surface tried (see the module docstring for the method and the figures). `source` names the
    surface in error messages and becomes the TetMesh's source.
    """
    points, triangles = _check_surface(surface_points, surface_triangles, source)
    if target_tets is not None and spacing is not None:
        raise TissueError(f"{source}: give target_tets or spacing, not both")
    volume = enclosed_volume(points, triangles)
    if volume < 0:
        triangles = triangles[:, ::-1]
        volume = -volume
    if not volume > 0:
        raise TissueError(f"{source}: the surface encloses no volume")
    surface = _Surface(points, triangles)
    lo, hi = points.min(axis=0), points.max(axis=0)

    if spacing is not None:
        if not np.isfinite(spacing) or spacing <= 0:
            raise TissueError(f"{source}: spacing must be positive, got {spacing}")
        h = float(spacing)
        shift = (0.0, 0.0, 0.0)
    else:
        target = 2000 if target_tets is None else int(target_tets)
        if not 8 <= target <= _MAX_LATTICE_TETS // 10:
            raise TissueError(f"{source}: target_tets must be between 8 and {_MAX_LATTICE_TETS // 10:,}, "
                              f"got {target_tets}")
        h, shift = _fit_spacing(surface, lo, hi, volume, target)
    lattice_tets = 12 * np.prod(np.ceil((hi - lo) / h) + 3)
    if lattice_tets > _MAX_LATTICE_TETS:
        raise TissueError(f"{source}: the spacing {h:.3g} is too fine for a surface of extent "
                          f"{np.round(hi - lo, 6).tolist()} ({lattice_tets:.3g} lattice tetrahedra)")
    x, tets = _mesh_at_spacing(surface, lo, hi, h, shift, _samples_for(points, triangles, h))
    if len(tets) == 0:
        raise TissueError(f"{source}: the spacing {h:.3g} is too coarse to fill the surface with any "
                          "tetrahedron")
    return TetMesh(x, tets, source=source)


def _samples_for(points, triangles, h: float):
    """Surface samples for the spreading step: about 40 per lattice cell face of area."""
    p = points[triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    return _surface_samples(points, triangles, int(np.clip(40 * area / h ** 2, 5000, 400_000)))


def _fit_spacing(surface: "_Surface", lo, hi, volume: float, target: int):
    """(spacing, lattice shift) whose stuffed count is nearest the target: secant steps on
    count ~ volume / h^3 (a BCC cube of edge h holds 12 tetrahedra), from a few lattice shifts
    when the count jumps past the target (a lattice-aligned box gains whole layers at once)."""
    h = (12.0 * volume / target) ** (1.0 / 3.0)
    tried = []
    for shift in _LATTICE_SHIFTS:
        for _ in range(5):
            count = len(_mesh_at_spacing(surface, lo, hi, h, shift)[1])
            tried.append((abs(count - target), h, tuple(shift)))
            if abs(count - target) <= 0.02 * target:
                return h, shift
            h *= (max(count, 1) / target) ** (1.0 / 3.0)
        h = min(tried)[1]
    _, h, shift = min(tried)
    return h, shift


# Lattice offsets (fractions of a cell) tried in turn when fitting a count.
_LATTICE_SHIFTS = np.array([[0.0, 0.0, 0.0], [0.37, 0.21, 0.13], [0.71, 0.55, 0.83], [0.19, 0.89, 0.47]])
