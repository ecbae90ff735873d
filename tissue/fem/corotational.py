"""Co-rotational linear tetrahedra (Felippa 2000; paper §2): element rotations, elastic forces and
stiffness products, accumulated element -> node in one of three ways.

Rotations: "large" (edge frames, SOFA's), "polar" (of F = R S; for an inverted element the closest
proper rotation, F = U Σ̂ Vᵀ with the smallest singular value negative and R = U Vᵀ: Irving et al.
2004; both in tissue.fem.rotations), "invertible" ("polar" plus a compression limit in that
diagonal frame: tissue.fem.compression_limit) and "linear" (none).

Per element we keep only the rest shape's inverse edge matrix `Dm⁻¹`, the volume, the Lamé
parameters and the current rotation `R` (20 numbers), not the 12×12 stiffness: the product `Kₑ u`
is computed as stress from strain, `f_a = -V R σ(ε(Rᵀ u)) g_a`, which is exactly `R Kₑ Rᵀ u` for the
linear tetrahedron and moves far fewer bytes.

Accumulation (paper Fig. 3):
  gather    one thread per element writes its 4 nodal vectors to a per-element buffer, then one
            thread per vertex sums its incident entries in a fixed order (deterministic);
  atomic    one thread per element adds to the nodes atomically;
  colouring elements are split into colours that share no node; one parallel loop per colour.
"""


import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..mesh import TetMesh
from .compression_limit import compressed, compression_stress, limit_tangent_stress, limited_directions
from .material import Material
from .model import MODEL, BodyModel, real_numpy
from .rotations import ROTATION_TOLERANCE, edge_frame, polar_rotation

# The per-step work of the FEM: element rotations, the principal directions (columns, rotated
# frame) in which each element's compression limit is active ("invertible"; zero otherwise) and
# the limit's curvature ψ''(σ̂) along each, the inverted-element count, and the gather buffer (4
# per element) or the atomic accumulator (per node), whichever the accumulation uses.
FEM_WORK = ti.types.argpack(R=ti.types.ndarray(), limited=ti.types.ndarray(), limit_curvature=ti.types.ndarray(),
                            inverted=ti.types.ndarray(), buffer=ti.types.ndarray(), accumulator=ti.types.ndarray())

ROTATIONS = ("large", "polar", "invertible", "linear")

# An element whose |det F| is at most this is (nearly) flat: its polar rotation is ill-defined, so it
# takes its edge frame's ("large") rotation instead.
FLAT_DETERMINANT = 1e-6
ACCUMULATIONS = ("gather", "atomic", "colouring")


def colour_elements(tets: np.ndarray, n_points: int) -> list[np.ndarray]:
    """Greedy colouring: elements of one colour share no node (so need no atomics)."""
    colour = np.full(len(tets), -1, dtype=np.int64)
    node_colours = [set() for _ in range(n_points)]
    for e, nodes in enumerate(tets):
        used = set().union(*(node_colours[v] for v in nodes))
        c = 0
        while c in used:
            c += 1
        colour[e] = c
        for v in nodes:
            node_colours[v].add(c)
    return [np.flatnonzero(colour == c).astype(np.int32) for c in range(colour.max() + 1)]


# ---- per-element mathematics, over a model's argpack `m` (tissue.fem.model) and the FEM's work `w`


@ti.func
def deformation_gradient(m: ti.template(), e, x: ti.template()):
    t = m.tets[e]
    Ds = ti.Matrix.cols([x[t[1]] - x[t[0]], x[t[2]] - x[t[0]], x[t[3]] - x[t[0]]])
    return Ds @ m.Dm_inv[e]


@ti.func
def element_rotation(m: ti.template(), e, x: ti.template(), rotation: ti.template(), tol):
    R = ti.Matrix.identity(float, 3)
    if ti.static(rotation == "large"):
        t = m.tets[e]
        R = edge_frame(x[t[0]], x[t[1]], x[t[2]]) @ m.rest_frame[e].transpose()
    elif ti.static(rotation == "polar" or rotation == "invertible"):
        F = deformation_gradient(m, e, x)
        if ti.abs(F.determinant()) > FLAT_DETERMINANT:
            R = polar_rotation(F, tol)
        else:  # (nearly) flat element: the edge frame is still well defined
            t = m.tets[e]
            R = edge_frame(x[t[0]], x[t[1]], x[t[2]]) @ m.rest_frame[e].transpose()
    return R


@ti.func
def linear_stress(m: ti.template(), e, G):
    """σ of the symmetric part of the displacement gradient G (linear isotropic)."""
    lam, mu = m.elastic[e][1], m.elastic[e][2]
    eps = 0.5 * (G + G.transpose())
    return 2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(float, 3)


@ti.func
def nodal_forces(m: ti.template(), R, e, G):
    """Forces (columns 1..3; node 0 balances them) of the linear stress of the displacement
    gradient G, given in the element's rotated frame: f = -V R σ(sym G) ∇N."""
    return -m.elastic[e][0] * R @ linear_stress(m, e, G) @ m.Dm_inv[e].transpose()


@ti.func
def element_stress(m: ti.template(), e, R, F):
    """The rotated-frame stress of the element at F: linear in RᵀF − I, plus the compression
    limit's where it is active."""
    G = R.transpose() @ F - ti.Matrix.identity(float, 3)
    sigma = linear_stress(m, e, G)
    S = 0.5 * (G + G.transpose()) + ti.Matrix.identity(float, 3)
    if compressed(S):
        sigma += compression_stress(m, e, S)
    return sigma


@ti.func
def elastic_force(m: ti.template(), w: ti.template(), e, x: ti.template(), rotation: ti.template()):
    """-R Kₑ (Rᵀ x - X) on the element's nodes, as a 3×3 (nodes 1..3; node 0 = -sum), plus the
    compression limit's force where the last rotation update found it active."""
    R = w.R[e]
    F = deformation_gradient(m, e, x)
    H = nodal_forces(m, R, e, R.transpose() @ F - ti.Matrix.identity(float, 3))
    if ti.static(rotation == "invertible"):
        if w.limited[e].norm_sqr() > 0.0:
            H = -m.elastic[e][0] * R @ element_stress(m, e, R, F) @ m.Dm_inv[e].transpose()
    return H


@ti.func
def stiffness_product(m: ti.template(), w: ti.template(), e, p: ti.template(), rotation: ti.template()):
    """-R Kₑ Rᵀ p on the element's nodes (the tangent stiffness times p, with its sign), with the
    compression limit's tangent where it is active (so the step is implicit in it too)."""
    R = w.R[e]
    G = R.transpose() @ deformation_gradient(m, e, p)
    H = nodal_forces(m, R, e, G)
    if ti.static(rotation == "invertible"):
        H -= m.elastic[e][0] * R @ limit_tangent_stress(w, e, G) @ m.Dm_inv[e].transpose()
    return H


@ti.func
def diagonal_block(m: ti.template(), w: ti.template(), e, corner, rotation: ti.template()):
    """The element's 3×3 stiffness block R Kₐₐ Rᵀ of one corner (for block-Jacobi)."""
    Dt = m.Dm_inv[e].transpose()
    g = ti.Vector([0.0, 0.0, 0.0])
    if corner == 0:
        g = -(ti.Vector([Dt[0, 0], Dt[1, 0], Dt[2, 0]]) + ti.Vector([Dt[0, 1], Dt[1, 1], Dt[2, 1]])
              + ti.Vector([Dt[0, 2], Dt[1, 2], Dt[2, 2]]))
    else:
        g = ti.Vector([Dt[0, corner - 1], Dt[1, corner - 1], Dt[2, corner - 1]])
    V, lam, mu = m.elastic[e][0], m.elastic[e][1], m.elastic[e][2]
    K = V * ((lam + mu) * g.outer_product(g) + mu * g.dot(g) * ti.Matrix.identity(float, 3))
    if ti.static(rotation == "invertible"):
        D = w.limited[e]
        if D.norm_sqr() > 0.0:
            k = w.limit_curvature[e]
            for i in ti.static(range(3)):
                d = ti.Vector([D[0, i], D[1, i], D[2, i]])
                K += (V * k[i] * g.dot(d) ** 2) * d.outer_product(d)
    return w.R[e] @ K @ w.R[e].transpose()


# ---- loops (parallel when called at kernel top level) ----------------------------------------


@ti.func
def update_rotations(m: ti.template(), w: ti.template(), x: ti.template(), rotation: ti.template(), tol):
    """Element rotations at x, where the compression limit is active and its curvature there
    ("invertible"), and the
    count of inverted elements (det F ≤ 0): a caller should hear of them."""
    w.inverted[0] = 0
    for e in range(m.counts[1]):
        R = element_rotation(m, e, x, rotation, tol)
        w.R[e] = R
        D = ti.Matrix.zero(float, 3, 3)
        k = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(rotation == "invertible"):
            G = R.transpose() @ deformation_gradient(m, e, x)
            S = 0.5 * (G + G.transpose())
            if compressed(S):
                D, k = limited_directions(m, e, S)
        w.limited[e] = D
        w.limit_curvature[e] = k
        t = m.tets[e]
        if (x[t[1]] - x[t[0]]).dot((x[t[2]] - x[t[0]]).cross(x[t[3]] - x[t[0]])) <= 0:
            w.inverted[0] += 1


@ti.func
def _deposit(m: ti.template(), w: ti.template(), e, H, accumulation: ti.template()):
    """Hand the element's nodal vectors (H: nodes 1..3 as columns) to the accumulation."""
    t = m.tets[e]
    f0 = -(ti.Vector([H[0, 0], H[1, 0], H[2, 0]]) + ti.Vector([H[0, 1], H[1, 1], H[2, 1]])
           + ti.Vector([H[0, 2], H[1, 2], H[2, 2]]))
    if ti.static(accumulation == "gather"):
        w.buffer[4 * e] = f0
        for a in ti.static(range(3)):
            w.buffer[4 * e + a + 1] = ti.Vector([H[0, a], H[1, a], H[2, a]])
    elif ti.static(accumulation == "atomic"):
        w.accumulator[t[0]] += f0
        for a in ti.static(range(3)):
            w.accumulator[t[a + 1]] += ti.Vector([H[0, a], H[1, a], H[2, a]])
    else:  # colouring: no two elements of a colour share a node, plain writes are safe
        w.accumulator[t[0]] = w.accumulator[t[0]] + f0
        for a in ti.static(range(3)):
            w.accumulator[t[a + 1]] = w.accumulator[t[a + 1]] + ti.Vector([H[0, a], H[1, a], H[2, a]])


@ti.func
def scatter_element(m: ti.template(), w: ti.template(), what: ti.template(), e, src: ti.template(),
                    accumulation: ti.template(), rotation: ti.template()):
    """One element's part of `what` ("force": elastic forces at positions src; "stiffness":
    tangent stiffness times src), handed to the accumulation."""
    H = ti.Matrix.zero(float, 3, 3)
    if ti.static(what == "force"):
        H = elastic_force(m, w, e, src, rotation)
    else:
        H = stiffness_product(m, w, e, src, rotation)
    _deposit(m, w, e, H, accumulation)


@ti.func
def scatter(m: ti.template(), w: ti.template(), what: ti.template(), src: ti.template(), accumulation: ti.template(),
            rotation: ti.template()):
    """Element stage of `what`; its nodal sums are then read with `gathered(v)`.
    Colouring is not fused here: it needs a launch per colour (see `scatter_launch`)."""
    ti.static_assert(accumulation != "colouring")
    for e in range(m.counts[1]):
        scatter_element(m, w, what, e, src, accumulation, rotation)


@ti.func
def gathered(m: ti.template(), w: ti.template(), v, accumulation: ti.template()):
    """The nodal sum of the last scatter at vertex v (read once: atomic/colouring reset it)."""
    s = ti.Vector([0.0, 0.0, 0.0])
    if ti.static(accumulation == "gather"):
        for k in range(m.valence[v]):
            s += w.buffer[m.incidence[v, k]]
    else:
        s = w.accumulator[v]
        w.accumulator[v] = ti.Vector([0.0, 0.0, 0.0])
    return s


@ti.func
def stiffness_diagonal(m: ti.template(), w: ti.template(), v, rotation: ti.template()):
    """Σ over incident elements of R Kₐₐ Rᵀ at vertex v."""
    K = ti.Matrix.zero(float, 3, 3)
    for k in range(m.valence[v]):
        c = m.incidence[v, k]
        K += diagonal_block(m, w, c // 4, c % 4, rotation)
    return K


# ---- standalone launches (tests, tools) ----------------------------------------------------------


@ti.kernel
def _rotations_kernel(m: MODEL, w: FEM_WORK, x: ti.types.ndarray(), rotation: ti.template(), tol: ti.f64):
    update_rotations(m, w, x, rotation, tol)


@ti.kernel
def _scatter_kernel(m: MODEL, w: FEM_WORK, what: ti.template(), src: ti.types.ndarray(), accumulation: ti.template(),
                    rotation: ti.template()):
    scatter(m, w, what, src, accumulation, rotation)


@ti.kernel
def _scatter_colour_kernel(m: MODEL, w: FEM_WORK, what: ti.template(), src: ti.types.ndarray(),
                           order: ti.types.ndarray(), begin: ti.i32, end: ti.i32, rotation: ti.template()):
    for i in range(begin, end):
        scatter_element(m, w, what, order[i], src, "colouring", rotation)


@ti.kernel
def _gather_kernel(m: MODEL, w: FEM_WORK, out: ti.types.ndarray(), accumulation: ti.template()):
    for v in range(m.counts[0]):
        out[v] = gathered(m, w, v, accumulation)


@ti.kernel
def _stress_kernel(m: MODEL, x: ti.types.ndarray(), out: ti.types.ndarray(), rotation: ti.template(), tol: ti.f64):
    for e in range(m.counts[1]):
        R = element_rotation(m, e, x, rotation, tol)
        F = deformation_gradient(m, e, x)
        sigma = linear_stress(m, e, R.transpose() @ F - ti.Matrix.identity(float, 3))
        if ti.static(rotation == "invertible"):
            sigma = element_stress(m, e, R, F)
        out[e] = R @ sigma @ R.transpose()


class CorotationalFEM:
    """The elastic part of one soft body: its model (`tissue.fem.model.BodyModel`), the choice of
    rotations and accumulation, and the per-step work they need (element rotations `R`, the gather
    buffer or the atomic accumulator, the inverted-element count).

    The Taichi functions of this module take `fem.model.pack` and `fem.work` and are called from
    the kernels of a solver (see `tissue.solver.ImplicitEuler`); the `*_numpy` methods launch them
    alone, for tests and tools.
    """

    def __init__(self, mesh: TetMesh | BodyModel, material: Material | None = None, rotation: str = "large",
                 accumulation: str = "gather"):
        if rotation not in ROTATIONS:
            raise TissueError(f"rotation: unknown method {rotation!r}; expected one of {ROTATIONS}")
        if accumulation not in ACCUMULATIONS:
            raise TissueError(f"accumulation: unknown method {accumulation!r}; expected one of {ACCUMULATIONS}")
        self.model = mesh if isinstance(mesh, BodyModel) else BodyModel(mesh, material)
        self.rotation, self.accumulation = rotation, accumulation
        # Writes of the element rotations R (the solver counts its steps' too): what was computed
        # from them (the multigrid's nodal rotations) holds while this count has not moved.
        self.rotation_writes = 0
        self.rotation_tolerance = ROTATION_TOLERANCE[backend.current().precision]
        self._version = None
        self._colouring = None       # (order, offsets) of the colouring ablation; edits drop it
        self.resize()
        self.model.subscribe(self)

    def topology_changed(self, edit) -> None:
        self._colouring = None

    def resize(self) -> bool:
        """Match the work arrays to the model's capacity; True when they were re-allocated."""
        model = self.model
        if self._version == model.version:
            return False
        real = backend.current().real
        vec3, mat3 = ti.types.vector(3, real), ti.types.matrix(3, 3, real)
        n, m = model.node_capacity, model.element_capacity
        self.R = ti.ndarray(mat3, m)      # every step recomputes the rotations before using them
        self.R.from_numpy(np.tile(np.eye(3, dtype=real_numpy()), (m, 1, 1)))
        self.rotation_writes += 1
        self.work_arrays = dict(R=self.R, limited=ti.ndarray(mat3, m), limit_curvature=ti.ndarray(vec3, m),
                                inverted=ti.ndarray(ti.i32, 1),
                                buffer=ti.ndarray(vec3, 4 * m if self.accumulation == "gather" else 1),
                                accumulator=ti.ndarray(vec3, n if self.accumulation != "gather" else 1))
        self.work = FEM_WORK(**self.work_arrays)
        self._io = [ti.ndarray(vec3, n) for _ in range(2)]
        self._stresses = ti.ndarray(mat3, m)     # element_stress_numpy's (kept: an allocation per call costs more)
        self._version = model.version
        return True

    @property
    def mesh(self) -> TetMesh:
        return self.model.mesh()

    @property
    def material(self) -> Material:
        return self.model.material

    @property
    def n_nodes(self) -> int:
        return self.model.n_nodes

    @property
    def n_elements(self) -> int:
        return self.model.n_elements

    def rotations(self) -> np.ndarray:
        """The element rotations of the last update (elements, 3, 3)."""
        return self.R.to_numpy()[:self.n_elements].astype(np.float64)

    # ---- standalone launches ---------------------------------------------------------------------

    def _vectors(self, values: np.ndarray, slot: int = 0):
        """One of two nodal arrays kept for the standalone launches, filled with `values`."""
        self.resize()
        array = self._io[slot]
        padded = np.zeros((array.shape[0], 3), dtype=real_numpy())
        padded[:self.n_nodes] = values
        array.from_numpy(padded)
        return array

    def scatter_launch(self, what: str, src) -> None:
        """The element stage as its own launch(es): one per colour when colouring."""
        m = self.model.pack
        if self.accumulation == "colouring":
            order, offsets = self._colours()
            for c in range(len(offsets) - 1):
                _scatter_colour_kernel(m, self.work, what, src, order, offsets[c], offsets[c + 1], self.rotation)
        else:
            _scatter_kernel(m, self.work, what, src, self.accumulation, self.rotation)

    def _colours(self):
        if self._colouring is None:
            colours = colour_elements(self.model.tets, self.n_nodes)
            self.n_colours = len(colours)
            order = ti.ndarray(ti.i32, self.n_elements)
            order.from_numpy(np.concatenate(colours))
            self._colouring = (order, [0] + [int(k) for k in np.cumsum([len(c) for c in colours])])
        return self._colouring

    def rotations_numpy(self, positions: np.ndarray) -> np.ndarray:
        """Element rotations (m, 3, 3) at the given positions (also stored for later products)."""
        self.rotation_writes += 1
        _rotations_kernel(self.model.pack, self.work, self._vectors(positions), self.rotation, self.rotation_tolerance)
        return self.rotations()

    def _gathered_numpy(self) -> np.ndarray:
        out = self._vectors(np.zeros((self.n_nodes, 3)), slot=1)
        _gather_kernel(self.model.pack, self.work, out, self.accumulation)
        return out.to_numpy()[:self.n_nodes]

    def elastic_forces_numpy(self, positions: np.ndarray, update_rotations: bool = True) -> np.ndarray:
        """Elastic nodal forces (n, 3) at the given positions."""
        x = self._vectors(positions)
        if update_rotations:
            self.rotation_writes += 1
            _rotations_kernel(self.model.pack, self.work, x, self.rotation, self.rotation_tolerance)
        self.scatter_launch("force", x)
        return self._gathered_numpy()

    def stiffness_product_numpy(self, vectors: np.ndarray) -> np.ndarray:
        """(-Σ R Kₑ Rᵀ) p with the current rotations."""
        self.scatter_launch("stiffness", self._vectors(vectors))
        return self._gathered_numpy()

    def element_stress_numpy(self, positions) -> np.ndarray:
        """Co-rotational stress R σ Rᵀ of each element (m, 3, 3) at the given positions: an (n, 3)
        array, or a nodal ndarray such as a solver's `x` (read in place)."""
        x = self._vectors(positions) if isinstance(positions, np.ndarray) else positions
        self.resize()
        out = self._stresses
        _stress_kernel(self.model.pack, x, out, self.rotation, self.rotation_tolerance)
        return out.to_numpy()[:self.n_elements].astype(np.float64)
