"""Co-rotational linear tetrahedra (Felippa 2000; paper §2): element rotations, elastic forces and
stiffness products, accumulated element -> node in one of three ways.

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
from .material import Material

ROTATIONS = ("large", "polar", "linear")
ACCUMULATIONS = ("gather", "atomic", "colouring")


def int_field(shape, n: int = 0):
    """An i32 field (a vector field of n components when n > 0) that leaves the next field 8-byte
    aligned: an odd number of 4-byte entries is followed by a 4-byte pad field.

    Taichi's gfx backends (Vulkan) pack root fields with no padding and address a 64-bit field that
    lands at an offset of 4 mod 8 one slot too low, silently overwriting the last entry of the field
    before it (taichi-dev/taichi#8803): e.g. the last node's `fixed` flag when the mesh has an odd
    number of nodes."""
    field = ti.Vector.field(n, ti.i32, shape) if n else ti.field(ti.i32, shape)
    if (int(np.prod(shape)) * max(n, 1)) % 2:
        ti.field(ti.i32, ())
    return field


def vertex_incidence(tets: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR index vertex -> (4 e + corner) of its incident element corners, sorted by element."""
    corners = np.arange(tets.size, dtype=np.int32)
    vertex = tets.reshape(-1)
    order = np.argsort(vertex, kind="stable")
    offsets = np.zeros(n_points + 1, dtype=np.int32)
    np.cumsum(np.bincount(vertex, minlength=n_points), out=offsets[1:])
    return offsets, corners[order]


def colour_elements(tets: np.ndarray, n_points: int) -> list[np.ndarray]:
    """Greedy colouring: elements of one colour share no node (so need no atomics)."""
    offsets, corner_ids = vertex_incidence(tets, n_points)
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


@ti.func
def edge_frame(a, b, c):
    """Orthonormal frame (columns) of a triangle: x along ab, z normal, as SOFA's "large"."""
    ex = (b - a).normalized()
    ez = ex.cross(c - a).normalized()
    ey = ez.cross(ex)
    return ti.Matrix.cols([ex, ey, ez])


@ti.func
def polar_rotation(F, tol):
    """Rotation of the polar decomposition F = R S by Higham's scaled Newton iteration.

    The scaling ζ = sqrt(‖X⁻¹‖/‖X‖) (Frobenius) needs only a square root, which every backend has
    in float64 (Vulkan's GLSL has no 64-bit pow, exp or trigonometry). An inverted element
    (det F < 0) gets the closest proper rotation: the orthogonal factor is reflected along the
    eigenvector of S with the smallest eigenvalue (Irving et al. 2004), found by inverse iteration
    (S is symmetric positive definite there).
    """
    X = F
    for _ in range(30):
        Xinv_t = X.inverse().transpose()
        zeta = ti.sqrt(Xinv_t.norm() / X.norm())
        Y = 0.5 * (zeta * X + Xinv_t / zeta)
        change = (Y - X).norm()
        X = Y
        if change <= tol:
            break
    if F.determinant() < 0:
        S = X.transpose() @ F
        S_inv = (0.5 * (S + S.transpose())).inverse()
        v = ti.Vector([0.8, 0.5, 0.33]).normalized()
        for _ in range(100):
            v = (S_inv @ v).normalized()
        X = X @ (ti.Matrix.identity(float, 3) - 2.0 * v.outer_product(v))
    return X


@ti.func
def nodal_rotation(Re: ti.template(), offsets: ti.template(), incidence: ti.template(), v, tol):
    """The orthonormalised average of the rotations of the elements around node v: the rotation
    of the polar decomposition of their mean X₀. Newton–Schulz, X ← X (3I - XᵀX) / 2, converges
    to it quadratically when the rotations are alike (X₀ nearly orthogonal: a few 3×3 products);
    otherwise (rotations far apart, or det X₀ ≤ 0) the scaled Newton iteration of the FEM."""
    X = ti.Matrix.zero(float, 3, 3)
    for k in range(offsets[v], offsets[v + 1]):
        X += Re[incidence[k] // 4]
    S = X / ti.max(offsets[v + 1] - offsets[v], 1)
    X = S
    done = False
    if S.determinant() > 0.0:
        for _ in range(12):
            E = X.transpose() @ X - ti.Matrix.identity(float, 3)
            e = E.norm()
            if e > 0.5:                             # too far from orthogonal for Newton–Schulz
                break
            X = X - 0.5 * (X @ E)
            if e <= tol:
                done = True
                break
    if not done:
        X = polar_rotation(S, tol)
    return X


@ti.data_oriented
class CorotationalFEM:
    """The elastic part of one soft body: rest data, rotations, forces and stiffness products.

    The Taichi functions here are meant to be called from the kernels of a solver (see
    `tissue.solver.ImplicitEuler`); the `*_numpy` methods launch them alone, for tests and tools.
    """

    def __init__(self, mesh: TetMesh, material: Material, rotation: str = "large",
                 accumulation: str = "gather"):
        if rotation not in ROTATIONS:
            raise TissueError(f"rotation: unknown method {rotation!r}; expected one of {ROTATIONS}")
        if accumulation not in ACCUMULATIONS:
            raise TissueError(f"accumulation: unknown method {accumulation!r}; expected one of {ACCUMULATIONS}")
        be = backend.current()
        real = be.real
        self.mesh, self.material = mesh, material
        self.rotation, self.accumulation = rotation, accumulation
        self.n_nodes, self.n_elements = mesh.n_points, mesh.n_tets
        self.rotation_tolerance = 1e-13 if be.precision == "f64" else 1e-6
        n, m = self.n_nodes, self.n_elements

        X = mesh.points
        Dm = np.stack([X[mesh.tets[:, i]] - X[mesh.tets[:, 0]] for i in (1, 2, 3)], axis=2)
        lam, mu = material.lame
        offsets, corners = vertex_incidence(mesh.tets, n)   # vertex -> element corners (gather, diagonal)
        colours = colour_elements(mesh.tets, n) if accumulation == "colouring" else []
        with backend.fields_of(self):
            self.tets = int_field(m, 4)
            self.rest = ti.Vector.field(3, real, n)
            self.Dm_inv = ti.Matrix.field(3, 3, real, m)
            self.rest_frame = ti.Matrix.field(3, 3, real, m)
            self.volume = ti.field(real, m)
            self.lame = ti.Vector.field(2, real, m)
            self.R = ti.Matrix.field(3, 3, real, m)
            self.inverted = int_field(())
            self.mass = ti.field(real, n)
            self.incidence_offsets = int_field(n + 1)
            self.incidence = int_field(4 * m)
            # Accumulation structures: only those of the chosen method are allocated.
            if accumulation == "gather":
                self.buffer = ti.Vector.field(3, real, 4 * m)
            else:
                self.accumulator = ti.Vector.field(3, real, n)
            if accumulation == "colouring":
                self.colour_order = int_field(m)
            self._io_fields = [ti.Vector.field(3, real, n) for _ in range(2)]

        self.tets.from_numpy(mesh.tets.astype(np.int32))
        self.rest.from_numpy(X)
        self.Dm_inv.from_numpy(np.linalg.inv(Dm))
        self.volume.from_numpy(mesh.volumes)
        self.lame.from_numpy(np.tile([lam, mu], (m, 1)))
        self.R.from_numpy(np.tile(np.eye(3), (m, 1, 1)))
        self._init_rest_frames()
        lumped = np.zeros(n)
        np.add.at(lumped, mesh.tets.reshape(-1), np.repeat(material.density * mesh.volumes / 4.0, 4))
        self.mass.from_numpy(lumped)
        self.incidence_offsets.from_numpy(offsets)
        self.incidence.from_numpy(corners)
        if accumulation == "colouring":
            self.n_colours = len(colours)
            self.colour_offsets = [0] + [int(k) for k in np.cumsum([len(c) for c in colours])]
            self.colour_order.from_numpy(np.concatenate(colours))

    @ti.kernel
    def _init_rest_frames(self):
        for e in range(self.n_elements):
            t = self.tets[e]
            self.rest_frame[e] = edge_frame(self.rest[t[0]], self.rest[t[1]], self.rest[t[2]])

    # ---- per-element mathematics -------------------------------------------------------------

    @ti.func
    def deformation_gradient(self, e, x):
        t = self.tets[e]
        Ds = ti.Matrix.cols([x[t[1]] - x[t[0]], x[t[2]] - x[t[0]], x[t[3]] - x[t[0]]])
        return Ds @ self.Dm_inv[e]

    @ti.func
    def element_rotation(self, e, x):
        R = ti.Matrix.identity(float, 3)
        if ti.static(self.rotation == "large"):
            t = self.tets[e]
            R = edge_frame(x[t[0]], x[t[1]], x[t[2]]) @ self.rest_frame[e].transpose()
        elif ti.static(self.rotation == "polar"):
            F = self.deformation_gradient(e, x)
            if ti.abs(F.determinant()) > 1e-6:
                R = polar_rotation(F, self.rotation_tolerance)
            else:  # (nearly) flat element: the edge frame is still well defined
                t = self.tets[e]
                R = edge_frame(x[t[0]], x[t[1]], x[t[2]]) @ self.rest_frame[e].transpose()
        return R

    @ti.func
    def nodal_forces(self, e, G):
        """Forces (columns 1..3; node 0 balances them) of the linear stress of the displacement
        gradient G, given in the element's rotated frame: f = -V R σ(sym G) ∇N."""
        lam, mu = self.lame[e][0], self.lame[e][1]
        eps = 0.5 * (G + G.transpose())
        sigma = 2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(float, 3)
        return -self.volume[e] * self.R[e] @ sigma @ self.Dm_inv[e].transpose()

    @ti.func
    def elastic_force(self, e, x):
        """-R Kₑ (Rᵀ x - X) on the element's nodes, as a 3×3 (nodes 1..3; node 0 = -sum)."""
        G = self.R[e].transpose() @ self.deformation_gradient(e, x) - ti.Matrix.identity(float, 3)
        return self.nodal_forces(e, G)

    @ti.func
    def stiffness_product(self, e, p):
        """-R Kₑ Rᵀ p on the element's nodes (the tangent stiffness times p, with its sign)."""
        return self.nodal_forces(e, self.R[e].transpose() @ self.deformation_gradient(e, p))

    @ti.func
    def diagonal_block(self, e, corner):
        """The element's 3×3 stiffness block R Kₐₐ Rᵀ of one corner (for block-Jacobi)."""
        Dt = self.Dm_inv[e].transpose()
        g = ti.Vector([0.0, 0.0, 0.0])
        if corner == 0:
            g = -(ti.Vector([Dt[0, 0], Dt[1, 0], Dt[2, 0]]) + ti.Vector([Dt[0, 1], Dt[1, 1], Dt[2, 1]])
                  + ti.Vector([Dt[0, 2], Dt[1, 2], Dt[2, 2]]))
        else:
            g = ti.Vector([Dt[0, corner - 1], Dt[1, corner - 1], Dt[2, corner - 1]])
        lam, mu = self.lame[e][0], self.lame[e][1]
        K = self.volume[e] * ((lam + mu) * g.outer_product(g) + mu * g.dot(g) * ti.Matrix.identity(float, 3))
        return self.R[e] @ K @ self.R[e].transpose()

    # ---- loops (parallel when called at kernel top level) ----------------------------------

    @ti.func
    def update_rotations(self, x):
        """Element rotations at x, and the count of inverted elements (det F ≤ 0): linear
        co-rotational elements have no inversion barrier, so a caller should hear of them."""
        self.inverted[None] = 0
        for e in range(self.n_elements):
            self.R[e] = self.element_rotation(e, x)
            t = self.tets[e]
            if (x[t[1]] - x[t[0]]).dot((x[t[2]] - x[t[0]]).cross(x[t[3]] - x[t[0]])) <= 0:
                self.inverted[None] += 1

    @ti.func
    def _deposit(self, e, H, out):
        """Hand the element's nodal vectors (H: nodes 1..3 as columns) to the accumulation."""
        t = self.tets[e]
        f0 = -(ti.Vector([H[0, 0], H[1, 0], H[2, 0]]) + ti.Vector([H[0, 1], H[1, 1], H[2, 1]])
               + ti.Vector([H[0, 2], H[1, 2], H[2, 2]]))
        if ti.static(self.accumulation == "gather"):
            self.buffer[4 * e] = f0
            for a in ti.static(range(3)):
                self.buffer[4 * e + a + 1] = ti.Vector([H[0, a], H[1, a], H[2, a]])
        elif ti.static(self.accumulation == "atomic"):
            out[t[0]] += f0
            for a in ti.static(range(3)):
                out[t[a + 1]] += ti.Vector([H[0, a], H[1, a], H[2, a]])
        else:  # colouring: no two elements of a colour share a node, plain writes are safe
            out[t[0]] = out[t[0]] + f0
            for a in ti.static(range(3)):
                out[t[a + 1]] = out[t[a + 1]] + ti.Vector([H[0, a], H[1, a], H[2, a]])

    @ti.func
    def scatter_element(self, what: ti.template(), e, src):
        """One element's part of `what` ("force": elastic forces at positions src; "stiffness":
        tangent stiffness times src), handed to the accumulation."""
        H = ti.Matrix.zero(float, 3, 3)
        if ti.static(what == "force"):
            H = self.elastic_force(e, src)
        else:
            H = self.stiffness_product(e, src)
        if ti.static(self.accumulation == "gather"):
            self._deposit(e, H, self.buffer)
        else:
            self._deposit(e, H, self.accumulator)

    @ti.func
    def scatter(self, what: ti.template(), src):
        """Element stage of `what`; its nodal sums are then read with `gathered(v)`.
        Colouring is not fused here: it needs a launch per colour (see `scatter_launch`)."""
        ti.static_assert(self.accumulation != "colouring")
        for e in range(self.n_elements):
            self.scatter_element(what, e, src)

    @ti.func
    def gathered(self, v):
        """The nodal sum of the last scatter at vertex v (read once: atomic/colouring reset it)."""
        s = ti.Vector([0.0, 0.0, 0.0])
        if ti.static(self.accumulation == "gather"):
            for k in range(self.incidence_offsets[v], self.incidence_offsets[v + 1]):
                s += self.buffer[self.incidence[k]]
        else:
            s = self.accumulator[v]
            self.accumulator[v] = ti.Vector([0.0, 0.0, 0.0])
        return s

    @ti.func
    def stiffness_diagonal(self, v):
        """Σ over incident elements of R Kₐₐ Rᵀ at vertex v."""
        K = ti.Matrix.zero(float, 3, 3)
        for k in range(self.incidence_offsets[v], self.incidence_offsets[v + 1]):
            c = self.incidence[k]
            K += self.diagonal_block(c // 4, c % 4)
        return K

    # ---- standalone launches (tests, tools) ---------------------------------------------------

    @ti.kernel
    def _rotations_kernel(self, x: ti.template()):
        self.update_rotations(x)

    @ti.kernel
    def _scatter_kernel(self, what: ti.template(), src: ti.template()):
        self.scatter(what, src)

    @ti.kernel
    def _scatter_colour_kernel(self, what: ti.template(), src: ti.template(), begin: ti.i32, end: ti.i32):
        for i in range(begin, end):
            self.scatter_element(what, self.colour_order[i], src)

    def scatter_launch(self, what: str, src) -> None:
        """The element stage as its own launch(es): one per colour when colouring."""
        if self.accumulation == "colouring":
            for c in range(self.n_colours):
                self._scatter_colour_kernel(what, src, self.colour_offsets[c], self.colour_offsets[c + 1])
        else:
            self._scatter_kernel(what, src)

    @ti.kernel
    def _gather_kernel(self, out: ti.template()):
        for v in out:
            out[v] = self.gathered(v)

    def _vector_field(self, values: np.ndarray, slot: int = 0):
        """One of two nodal fields kept for the standalone launches, filled with `values`.

        Reused from call to call: a new field per call would be a new template argument, so every
        call would compile its kernels again."""
        f = self._io_fields[slot]
        f.from_numpy(np.asarray(values, dtype=np.float64 if self.R.dtype == ti.f64 else np.float32))
        return f

    def rotations_numpy(self, positions: np.ndarray) -> np.ndarray:
        """Element rotations (m, 3, 3) at the given positions (also stored for later products)."""
        self._rotations_kernel(self._vector_field(positions))
        return self.R.to_numpy()

    def elastic_forces_numpy(self, positions: np.ndarray, update_rotations: bool = True) -> np.ndarray:
        """Elastic nodal forces (n, 3) at the given positions."""
        x = self._vector_field(positions)
        if update_rotations:
            self._rotations_kernel(x)
        out = self._vector_field(np.zeros((self.n_nodes, 3)), slot=1)
        self.scatter_launch("force", x)
        self._gather_kernel(out)
        return out.to_numpy()

    def stiffness_product_numpy(self, vectors: np.ndarray) -> np.ndarray:
        """(-Σ R Kₑ Rᵀ) p with the current rotations."""
        p = self._vector_field(vectors)
        out = self._vector_field(np.zeros((self.n_nodes, 3)), slot=1)
        self.scatter_launch("stiffness", p)
        self._gather_kernel(out)
        return out.to_numpy()

    @ti.kernel
    def _stress_kernel(self, x: ti.template(), out: ti.template()):
        for e in range(self.n_elements):
            R = self.element_rotation(e, x)
            G = R.transpose() @ self.deformation_gradient(e, x) - ti.Matrix.identity(float, 3)
            eps = 0.5 * (G + G.transpose())
            lam, mu = self.lame[e][0], self.lame[e][1]
            sigma = 2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(float, 3)
            out[e] = R @ sigma @ R.transpose()

    def element_stress_numpy(self, positions) -> np.ndarray:
        """Co-rotational stress R σ Rᵀ of each element (m, 3, 3) at the given positions: an (n, 3)
        array, or a nodal Taichi field such as a solver's `x` (read in place)."""
        if not hasattr(self, "_stress_field"):   # allocated on first use, so the kernel compiles once
            with backend.fields_of(self):
                self._stress_field = ti.Matrix.field(3, 3, self.R.dtype, self.n_elements)
        x = self._vector_field(positions) if isinstance(positions, np.ndarray) else positions
        self._stress_kernel(x, self._stress_field)
        return self._stress_field.to_numpy().astype(np.float64)
