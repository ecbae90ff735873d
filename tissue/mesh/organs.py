"""Procedural organs: closed surfaces of a liver, a stomach and a colon segment, and their
tetrahedral meshes.

No patient data ships with `tissue`, so the abdomen of the paper's scenes is modelled: each organ is
an implicit function (negative inside) sampled on a grid, its zero level extracted with marching
cubes (VTK's, `tissue.mesh.isosurface`), Taubin-smoothed, decimated to a few thousand triangles, and checked to be closed,
manifold and oriented outward (tests/test_organs.py also checks it is free of self-intersections).
The shapes are deterministic; each surface is built once per process (about a second) and copied
out.

All three share one frame, in metres, with the axes of DICOM's patient coordinates (LPS): x toward
the patient's left, y toward the back (posterior), z toward the head (superior). Placed as returned
they sit roughly as in the body without touching: the liver's right lobe on the patient's right,
the stomach's fundus tucked under the left lobe (gap about 4 mm), the transverse colon below the
stomach (gap about 7 mm).

    liver_surface()    a large right lobe and a thinner left lobe parted by a notch, a convex
                       diaphragmatic (upper) face, a concave visceral (lower) face and a sharp-ish
                       (8 mm) anterior-inferior edge; 0.20 m wide (x), 0.15 m deep (y), 0.10 m
                       high (z); 0.93 litre
    stomach_surface()  a J-shaped bag: the fundus dome up on the left, the body descending, the
                       antrum turning right and up, narrowing to the pylorus; 0.27 m along its
                       curve, 1.1 litre
    colon_surface()    a transverse-colon segment: a tube with haustra (bulges between folds)
                       and three taeniae along a sagging centreline, closed at both ends; 0.29 m
                       long, 0.6 litre

`organ_surface(name)` and `organ_mesh(name, target_tets=1300)` reach them by name (see `ORGANS`).
The liver reaches the paper's resolutions (1,300, 1,600 and 3,900 tetrahedra) through `target_tets`.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..errors import TissueError
from .tetmesh import TetMesh


def _smoothstep(e0: float, e1: float, x):
    t = np.clip((np.asarray(x, dtype=np.float64) - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _smooth_max(a, b, k: float):
    """A max with its corner rounded over a width k (polynomial smooth maximum)."""
    h = np.clip(0.5 - 0.5 * (a - b) / k, 0.0, 1.0)
    return a * (1.0 - h) + b * h + k * h * (1.0 - h)


# --------------------------------------------------------------------------------------------
# Implicit shapes (negative inside), evaluated on (n, 3) points


def _liver_implicit(p: np.ndarray) -> np.ndarray:
    """A thick-to-thin body over a planform: the thickness and the height of the mid-surface are
    functions of (x, y); the lower and upper faces share the thickness between them."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    # Planform (seen from above): u runs across the body from the right lobe's rounded end (-1)
    # to the left lobe's tip (+1); the right lobe is deep (front to back), the left lobe shallower
    # and further forward.
    u = (x + 0.03) / 0.10
    depth = 0.034 + 0.041 * _smoothstep(0.85, -0.35, u)  # half-depth in y
    y_centre = -0.014 * _smoothstep(-0.3, 0.7, u)
    v = (y - y_centre) / depth
    m = 2.4
    r = (np.abs(u) ** m + np.abs(v) ** m) ** (1.0 / m)
    # Notches between the lobes: on the anterior edge (round ligament) and at the back
    # (ligamentum venosum), giving the planform a waist.
    r = r + 0.18 * np.exp(-((u - 0.10) / 0.08) ** 2) * _smoothstep(-0.3, -1.0, v)
    r = r + 0.10 * np.exp(-((u - 0.05) / 0.10) ** 2) * _smoothstep(0.3, 1.0, v)
    # Thickness: thick at the back of the right lobe, thinner toward the front and the left lobe;
    # a broad dome (1 - r^3) that is rounded at the back (exponent 1/2) and wedge-like toward the
    # front (exponent up to 1.2), ending in an 8 mm rim (a sharp-ish edge).
    lobe = 0.034 + 0.056 * _smoothstep(0.40, -0.30, u)
    thickness = lobe * (0.55 + 0.45 * _smoothstep(-1.0, 0.9, v))
    exponent = 0.5 + 0.45 * _smoothstep(0.1, -0.9, v) + 0.25 * _smoothstep(0.3, 0.9, u)
    t = thickness * np.maximum(1.0 - np.abs(r) ** 3, 0.0) ** exponent + 0.008
    # The share of the thickness below the mid-surface: even at the back (rounded), small at the
    # front (the visceral face rises to meet the diaphragmatic face at the inferior edge).
    below = 0.15 + 0.35 * _smoothstep(-0.8, 0.8, v)
    # The lower (visceral) face is concave: the inferior edge hangs down at the front, the face
    # rises behind it where the colon and kidney (right) and the stomach (left) press on it, and
    # comes down again to the rounded back.
    base = (0.020 * np.exp(-((u + 0.30) / 0.45) ** 2 - ((v - 0.05) / 0.7) ** 2)
            + 0.012 * np.exp(-((u - 0.50) / 0.30) ** 2 - ((v + 0.1) / 0.6) ** 2)
            - 0.030 * _smoothstep(-0.1, -1.0, v))
    z_bottom = base - below * t
    z_top = base + (1.0 - below) * t
    vertical = np.maximum(z_bottom - z, z - z_top)
    across = (r - 1.0) * depth  # roughly the distance outside the planform, in metres
    return _smooth_max(vertical, across, 0.006)


def _sample_curve(control: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points evenly spaced by arc length along a Catmull-Rom spline through `control`, and
    their arc length."""
    c = np.asarray(control, dtype=np.float64)
    ext = np.vstack([2 * c[0] - c[1], c, 2 * c[-1] - c[-2]])
    dense = []
    for i in range(1, len(ext) - 2):
        p0, p1, p2, p3 = ext[i - 1], ext[i], ext[i + 1], ext[i + 2]
        t = np.linspace(0.0, 1.0, 200, endpoint=False)[:, None]
        dense.append(0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t ** 2
                            + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3))
    dense.append(c[-1:])
    dense = np.vstack(dense)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    s_even = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(s_even, s, dense[:, d]) for d in range(3)], axis=1), s_even


# The stomach's centreline (LPS, metres): from the fundus high on the left, the body down, the
# antrum turning to the right and up, to the pylorus; the radius along it (fraction of length ->
# radius); and the dome of the fundus, bulging up and outward above the cardia.
_STOMACH_CENTRELINE = np.array([
    [0.080, 0.035, -0.025], [0.085, 0.020, -0.070], [0.075, 0.005, -0.110],
    [0.050, -0.008, -0.140], [0.015, -0.015, -0.152], [-0.020, -0.015, -0.140],
    [-0.045, -0.010, -0.120], [-0.055, 0.000, -0.098]])
_STOMACH_RADIUS = np.array([[0.0, 0.042], [0.15, 0.046], [0.40, 0.042], [0.62, 0.031], [0.85, 0.018],
                            [1.0, 0.012]])
_FUNDUS_CENTRE = np.array([0.092, 0.035, -0.020])
_FUNDUS_RADII = np.array([0.044, 0.038, 0.042])


# How far outside a shape (m) an implicit may return any positive value in place of its own:
# marching cubes reads values at the corners of the cells the surface crosses (within a cell
# diagonal of it) and _extract's gradient their neighbours', so a value only needs to be exact
# within two cells of the surface; 20 mm is eight of the stomach's 2.5 mm cells, room for slopes up
# to about 3 (the implicits are near distances there: slope about 1).
_SIGN_ONLY = 0.02

# Leaf size of the k-d trees over a centreline's samples: the grid's hundreds of thousands of queries
# each reach many of the dense samples, and scan larger leaves in fewer descents (the neighbours
# found are the same for any leaf size).
_CURVE_LEAF = 64


def _stomach_implicit(p: np.ndarray) -> np.ndarray:
    """A sphere sweep along the J-shaped centreline, flattened front to back, smoothly joined
    to the fundus dome."""
    from scipy.spatial import cKDTree

    curve, s = _sample_curve(_STOMACH_CENTRELINE, 600)
    radius = np.interp(s / s[-1], _STOMACH_RADIUS[:, 0], _STOMACH_RADIUS[:, 1])
    flatten = np.array([1.0, 1.0 / 0.8, 1.0])  # the bag is thinner front to back
    centre_y = curve[:, 1].mean()
    q = (p - [0.0, centre_y, 0.0]) * flatten
    c = (curve - [0.0, centre_y, 0.0]) * flatten
    tree, dome, k = cKDTree(c, leafsize=_CURVE_LEAF), _ellipsoid(p, _FUNDUS_CENTRE, _FUNDUS_RADII), 0.015
    # A lower bound of the value, cheap: the sweep is at least (distance to the nearest sphere
    # centre) − (largest radius), and the smooth maximum at most k/4 above the maximum. Where the
    # bound lies beyond _SIGN_ONLY the value only needs its sign (see _extract) and the bound is
    # kept: the 12-neighbour query, most of the surface's cost, runs on the rest.
    nearest = _distance_lower_bound(tree, p, [0.0, centre_y, 0.0], flatten)
    value = np.minimum(nearest - radius.max(), dome) - k / 4
    near = value <= _SIGN_ONLY
    # Distance minus radius, minimised over nearby sweep spheres.
    dist, idx = tree.query(q[near], k=12, workers=-1)
    sweep = (dist - radius[idx]).min(axis=1)
    value[near] = -_smooth_max(-sweep, -dome[near], k)
    return value


def _distance_lower_bound(tree, p: np.ndarray, origin=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A lower bound of each point's distance to the tree's points, the tree built on points mapped
    by q = (x - origin) * scale, in that space; cheap: the distance of the nearest node of a 1 cm
    grid, less the farthest a point lies from its node (in q)."""
    spacing, lo = 0.01, p.min(axis=0)
    shape = np.ceil((p.max(axis=0) - lo) / spacing).astype(int) + 1
    nodes = lo + spacing * np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1).reshape(-1, 3)
    at_node, _ = tree.query((nodes - origin) * scale, k=1)
    node = np.ravel_multi_index(np.rint((p - lo) / spacing).astype(int).T, shape)
    return at_node[node] - 0.5 * spacing * np.linalg.norm(scale)


def _ellipsoid(p: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (exact on the axes)."""
    d = (p - centre) / radii
    k0 = np.linalg.norm(d, axis=1)
    k1 = np.linalg.norm(d / radii, axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


_COLON_CENTRELINE = np.array([
    [-0.125, 0.010, -0.184], [-0.080, -0.010, -0.209], [-0.030, -0.025, -0.222],
    [0.020, -0.025, -0.222], [0.070, -0.010, -0.209], [0.120, 0.015, -0.184]])


# The colon's radius at its haustra, its largest: 0.024 m × (1 + 0.22 − 0.08), see _colon_value.
_COLON_RADIUS_MAX = 0.024 * 1.14


def _colon_implicit(p: np.ndarray) -> np.ndarray:
    """A tube around the centreline whose radius bulges between folds (haustra) and dips at three
    longitudinal bands (taeniae); hemispherical ends. Exact where it can reach marching cubes: a
    cheap lower bound (distance to the centreline less the largest radius) where that bound lies
    beyond _SIGN_ONLY, as the stomach's."""
    from scipy.spatial import cKDTree

    curve, s = _sample_curve(_COLON_CENTRELINE, 800)
    tree = cKDTree(curve, leafsize=_CURVE_LEAF)
    value = _distance_lower_bound(tree, p) - _COLON_RADIUS_MAX
    near = value <= _SIGN_ONLY
    value[near] = _colon_value(p[near], tree, curve, s)
    return value


def _colon_value(p: np.ndarray, tree, curve: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The colon's implicit at p: distance to the centreline (sampled as `curve`, arc length `s`,
    `tree` over it) less the local radius."""
    tangent = np.gradient(curve, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    # A frame without twist: the normal is the component of +z across the tangent.
    normal = np.array([0.0, 0.0, 1.0]) - tangent[:, 2:3] * tangent
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    _, i = tree.query(p, workers=-1)
    d = p - curve[i]
    dist = np.linalg.norm(d, axis=1)
    theta = np.arctan2(np.einsum("ij,ij->i", d, binormal[i]), np.einsum("ij,ij->i", d, normal[i]))
    length = s[-1]
    # Haustra: bulges every 32 mm separated by narrow folds; faded out toward the closed ends.
    phase = np.abs(np.sin(np.pi * s[i] / 0.032 + 0.6))
    fade = _smoothstep(0.0, 0.02, s[i]) * _smoothstep(length, length - 0.02, s[i])
    bulge = 1.0 + fade * (0.22 * phase ** 0.7 - 0.08)
    taeniae = 1.0 - fade * 0.10 * np.maximum(np.cos(3.0 * theta - 0.5), 0.0) ** 16
    radius = 0.024 * bulge * taeniae
    return dist - radius


# --------------------------------------------------------------------------------------------
# Surfaces


def _extract(implicit, lo, hi, grid_spacing: float, target_triangles: int, smooth_iterations: int = 20):
    """Marching cubes on a grid, largest component, Taubin smoothing, decimation; returns
    (points, triangles) oriented outward, checked closed and manifold."""
    from .closed_surface import enclosed_volume, surface_edges_report
    from .isosurface import decimated, sampling_grid, smoothed_zero_level, surface_arrays

    lo = np.asarray(lo, dtype=np.float64) - 3 * grid_spacing
    hi = np.asarray(hi, dtype=np.float64) + 3 * grid_spacing
    dims = np.ceil((hi - lo) / grid_spacing).astype(int) + 1
    grid, pts = sampling_grid(lo, dims, grid_spacing)
    # The grid's points run x fastest; evaluate the implicit on them in chunks.
    values = np.concatenate([implicit(pts[i:i + 400_000]) for i in range(0, len(pts), 400_000)])
    if values.min() >= 0:
        raise TissueError("procedural organ: the implicit shape is empty")
    cube = values.reshape(dims[::-1])  # (z, y, x)
    faces = [cube[0], cube[-1], cube[:, 0], cube[:, -1], cube[:, :, 0], cube[:, :, -1]]
    if min(f.min() for f in faces) <= 0:
        raise TissueError("procedural organ: the shape reaches the edge of its sampling grid")
    # Divide by the gradient's length: the zero level stays, but the field becomes close to a
    # distance there, which marching cubes interpolates well (height-field implicits are steep).
    gradient = np.gradient(cube, grid_spacing)
    slope = np.sqrt(sum(g * g for g in gradient)).ravel()
    surf = smoothed_zero_level(grid, values / np.maximum(slope, 1e-3), smooth_iterations, pass_band=0.05)
    if surf.GetNumberOfCells() > target_triangles:
        fewer = decimated(surf, 1.0 - target_triangles / surf.GetNumberOfCells())
        if surface_edges_report(surface_arrays(fewer)[1]) == (0, 0, 0):
            surf = fewer
    points, triangles = surface_arrays(surf)
    boundary, non_manifold, misoriented = surface_edges_report(triangles)
    if boundary or non_manifold or misoriented:
        raise TissueError(f"procedural organ: surface extraction gave {boundary} open, {non_manifold} "
                          f"non-manifold and {misoriented} misoriented edges")
    if enclosed_volume(points, triangles) < 0:
        triangles = triangles[:, ::-1].copy()
    return points, triangles


@lru_cache(maxsize=None)
def _cached(name: str):
    """The organ's surface, made once per machine (the mesh cache keeps it): a mesh of the organ
    with another number of tetrahedra starts from it, without marching cubes (nor VTK)."""
    from .cache import cached_arrays

    surface = cached_arrays(lambda: dict(zip(("points", "triangles"), _surface(name))), ("points", "triangles"),
                            "organ_surface", name=name)
    return surface["points"], surface["triangles"]


def _surface(name: str):
    if name == "liver":
        return _extract(_liver_implicit, (-0.135, -0.09, -0.07), (0.075, 0.085, 0.085), 0.0015, 5000,
                        smooth_iterations=60)
    if name == "stomach":
        return _extract(_stomach_implicit, (-0.08, -0.05, -0.20), (0.14, 0.08, 0.03), 0.0025, 4000)
    if name == "colon":
        return _extract(_colon_implicit, (-0.16, -0.06, -0.26), (0.16, 0.05, -0.15), 0.002, 6000,
                        smooth_iterations=10)
    raise TissueError(f"unknown organ {name!r} (expected one of {', '.join(ORGANS)})")


def _copy(name: str) -> tuple[np.ndarray, np.ndarray]:
    points, triangles = _cached(name)
    return points.copy(), triangles.copy()


def liver_surface() -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64 in metres, triangles (m, 3) int64) of the liver: closed, oriented
    outward, 5,000 triangles."""
    return _copy("liver")


def stomach_surface() -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of the stomach: closed, oriented outward, 4,000 triangles."""
    return _copy("stomach")


def colon_surface() -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of a transverse-colon segment: closed, oriented outward, ~6,000
    triangles."""
    return _copy("colon")


ORGANS = {"liver": liver_surface, "stomach": stomach_surface, "colon": colon_surface}


def organ_surface(name: str) -> tuple[np.ndarray, np.ndarray]:
    """The closed surface of the organ called `name` ("liver", "stomach" or "colon")."""
    if name not in ORGANS:
        raise TissueError(f"unknown organ {name!r} (expected one of {', '.join(ORGANS)})")
    return ORGANS[name]()


def organ_mesh(name: str, target_tets: int = 1300) -> TetMesh:
    """The organ called `name` filled with about `target_tets` tetrahedra (within a few per cent;
    see `tissue.mesh.tetrahedralize` for the method and the quality reached). Made once per machine:
    later calls load it from the mesh cache (`tissue.mesh.cache`)."""
    from .cache import cached_mesh

    def make():
        from .tetrahedralize import tetrahedralize

        points, triangles = organ_surface(name)
        return tetrahedralize(points, triangles, target_tets=target_tets, source=f"organ:{name}")

    return cached_mesh(make, "organ", name=name, tets=int(target_tets))
