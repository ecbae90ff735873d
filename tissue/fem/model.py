"""What a soft body *is*: rest shape, element rest data, material per element, lumped mass, held
nodes and the gather index, in capacity-sized storage with active counts, edited in place.

The arrays are Taichi ndarrays: a kernel over `ti.types.ndarray()` arguments compiles once per
element type and then serves arrays of any size, so a body of another mesh, or a body whose
topology changed, reuses every compiled kernel. The numpy mirrors are the source of truth for
edits; an edit changes them and uploads what changed. When an edit needs more room than the
capacity, the arrays double (`growths` counts it) and `version` tells the state and the operators
built on the model to resize theirs; nothing recompiles.

Elements are kept compact: removing element e moves the last element into its slot (the
returned map says where every element went). Nodes are never removed: a node left without
elements is `DETACHED` and the solver keeps it still.

Kernels read a model through its argpack (`model.pack`):
    counts      i32 (2,): nodes, elements in use
    rest        vec3 (nodes)         held  i32 (nodes): 0 free, HELD, DETACHED
    mass        real (nodes)         lumped, Σ ρ V / 4 over incident elements
    tets        vec4 i32 (elements)
    Dm_inv      mat3 (elements)      inverse rest edge matrix
    rest_frame  mat3 (elements)      rest edge frame (SOFA's "large" rotations)
    elastic     vec3 (elements)      V, λ, μ
    valence     i32 (nodes)          incident element corners of each node …
    incidence   i32 (nodes, slots)   … as 4 e + corner, the first `valence` slots of each row
"""


import weakref
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..launch import replayed
from ..mesh import TetMesh
from ..mesh.topology import OUTWARD_FACES
from ..mesh.tetmesh import signed_volumes
from .material import Material

HELD, DETACHED = 1, 2
MODEL = ti.types.argpack(counts=ti.types.ndarray(), rest=ti.types.ndarray(), held=ti.types.ndarray(),
                         mass=ti.types.ndarray(), tets=ti.types.ndarray(), Dm_inv=ti.types.ndarray(),
                         rest_frame=ti.types.ndarray(), elastic=ti.types.ndarray(),
                         valence=ti.types.ndarray(), incidence=ti.types.ndarray())


def real_numpy():
    return np.float64 if backend.current().precision == "f64" else np.float32


def edge_frames(points: np.ndarray) -> np.ndarray:
    """Orthonormal frames (columns) of triangles (k, 3, 3): x along ab, z normal (SOFA's "large")."""
    a, b, c = points[:, 0], points[:, 1], points[:, 2]
    ex = b - a
    ex /= np.linalg.norm(ex, axis=1, keepdims=True)
    ez = np.cross(ex, c - a)
    ez /= np.linalg.norm(ez, axis=1, keepdims=True)
    return np.stack([ex, np.cross(ez, ex), ez], axis=2)


@dataclass(frozen=True)
class Edit:
    """What one topology edit did, for the structures built on the model (`BodyModel.subscribe`):
    elements `added` (ids), and elements moved from `moved_from` to `moved_to` to fill the slots
    of removed ones."""

    added: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    moved_from: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    moved_to: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


class BodyModel:
    """The rest state of one soft body; see the module docstring."""

    def __init__(self, mesh: TetMesh, material: Material, node_capacity: int | None = None,
                 element_capacity: int | None = None, slots: int | None = None):
        n, m = mesh.n_points, mesh.n_tets
        self.material = material
        self.n_nodes, self.n_elements = 0, 0
        self.version = 0      # bumped whenever the arrays are re-allocated (growth)
        self.edits = 0        # bumped whenever the device arrays are written (what reads them may cache)
        self.growths = 0
        self._real = real_numpy()
        self._faces = None
        self._face_array = None     # the boundary faces as an array (read-only), rebuilt after edits
        self._staging = None        # the edit rows' host buffers, reused (see _flush)
        self._counts = np.zeros(2, dtype=np.int32)
        self._subscribers: list[weakref.ref] = []
        valence = np.bincount(mesh.tets.reshape(-1), minlength=n)
        self._allocate(max(node_capacity or n, n), max(element_capacity or m, m),
                       max(slots or int(valence.max()) + 4, int(valence.max())))
        self.add_nodes(mesh.points)
        self.add_elements(mesh.tets, material)
        self.source = mesh.source

    # ---- storage -----------------------------------------------------------------------------

    def _allocate(self, nodes: int, elements: int, slots: int) -> None:
        old = getattr(self, "_rest", None)
        real = backend.current().real

        def grown(name, shape, dtype, fill=0):
            array = np.full(shape, fill, dtype=dtype)
            if old is not None:
                previous = getattr(self, name)
                array[tuple(slice(0, s) for s in previous.shape)] = previous
            return array

        self._rest = grown("_rest", (nodes, 3), np.float64)
        self._held = grown("_held", nodes, np.int32)
        self._mass = grown("_mass", nodes, np.float64)
        self._valence = grown("_valence", nodes, np.int32)
        self._incidence = grown("_incidence", (nodes, slots), np.int32, -1)
        self._tets = grown("_tets", (elements, 4), np.int32)
        self._Dm_inv = grown("_Dm_inv", (elements, 3, 3), np.float64)
        self._rest_frame = grown("_rest_frame", (elements, 3, 3), np.float64)
        self._elastic = grown("_elastic", (elements, 3), np.float64)
        self._density = grown("_density", elements, np.float64)
        self.arrays = dict(
            counts=ti.ndarray(ti.i32, 2),
            rest=ti.ndarray(ti.types.vector(3, real), nodes),
            held=ti.ndarray(ti.i32, nodes),
            mass=ti.ndarray(real, nodes),
            tets=ti.ndarray(ti.types.vector(4, ti.i32), elements),
            Dm_inv=ti.ndarray(ti.types.matrix(3, 3, real), elements),
            rest_frame=ti.ndarray(ti.types.matrix(3, 3, real), elements),
            elastic=ti.ndarray(ti.types.vector(3, real), elements),
            valence=ti.ndarray(ti.i32, nodes),
            incidence=ti.ndarray(ti.i32, (nodes, slots)))
        self.pack = MODEL(**self.arrays)
        if old is not None:
            self.version += 1
            self.growths += 1
            self._upload(*self.arrays)

    @property
    def node_capacity(self) -> int:
        return len(self._rest)

    @property
    def element_capacity(self) -> int:
        return len(self._tets)

    def reserve(self, nodes: int = 0, elements: int = 0, slots: int = 0) -> None:
        """Room for this many more nodes and elements, and for `slots` elements at a node, now
        (e.g. before cutting), so that the edits to come do not grow the arrays (and what is
        sized by them) midway. Exactly that room: what is sized by the square of the nodes (a
        cutting compliance) would pay for more."""
        self._reserve(nodes=nodes, elements=elements, slots=slots, factor=1)

    def _reserve(self, nodes: int = 0, elements: int = 0, slots: int = 0, factor: int = 2) -> None:
        """Room for this many more nodes and elements and slots per node; what is short grows to
        `factor` times what there is (doubling: rare growth under edits), or to the need."""
        def grown(need, have):
            return have if need <= have else max(need, factor * have)

        have = (self.node_capacity, self.element_capacity, self._incidence.shape[1])
        want = (grown(self.n_nodes + nodes, have[0]), grown(self.n_elements + elements, have[1]), grown(slots, have[2]))
        if want != have:
            self._allocate(*want)

    def _upload(self, *names: str) -> None:
        self.edits += 1
        real = self._real
        for name in names:
            if name == "counts":
                self.arrays["counts"].from_numpy(np.array([self.n_nodes, self.n_elements], dtype=np.int32))
                continue
            values = getattr(self, "_" + name)
            self.arrays[name].from_numpy(values.astype(real) if values.dtype == np.float64 else values)

    # ---- what the rest of the code reads -------------------------------------------------------

    @property
    def tets(self) -> np.ndarray:
        return self._tets[:self.n_elements]

    @property
    def points(self) -> np.ndarray:
        return self._rest[:self.n_nodes]

    @property
    def mass(self) -> np.ndarray:
        return self._mass[:self.n_nodes]

    @property
    def held(self) -> np.ndarray:
        return self._held[:self.n_nodes]

    @property
    def elastic(self) -> np.ndarray:
        """(elements, 3): volume, λ, μ of each element."""
        return self._elastic[:self.n_elements]

    @property
    def Dm_inv(self) -> np.ndarray:
        return self._Dm_inv[:self.n_elements]

    @property
    def density(self) -> np.ndarray:
        """(elements,) mass density of each element."""
        return self._density[:self.n_elements]

    @property
    def volumes(self) -> np.ndarray:
        return self._elastic[:self.n_elements, 0]

    @property
    def incidence_rows(self) -> np.ndarray:
        """(node capacity, slots) corner codes 4 e + a of each node's elements; −1 past its valence."""
        return self._incidence

    @property
    def incidence_capacity(self) -> int:
        return self._incidence.size

    def mesh(self) -> TetMesh:
        """The elements in use as a TetMesh (all nodes kept, detached ones too)."""
        return TetMesh(self.points.copy(), self.tets.astype(np.int64), source=self.source)

    def gather_index(self):
        """(valence, incidence) ndarrays, for kernels outside the solver's (the nodal rotations)."""
        return self.arrays["valence"], self.arrays["incidence"]

    def incidence_csr(self) -> tuple[np.ndarray, np.ndarray]:
        """The gather index as CSR: offsets (nodes + 1) and corner codes 4 e + a."""
        valence = self._valence[:self.n_nodes]
        offsets = np.zeros(self.n_nodes + 1, dtype=np.int32)
        np.cumsum(valence, out=offsets[1:])
        rows = self._incidence[:self.n_nodes]
        return offsets, rows[np.arange(rows.shape[1]) < valence[:, None]]

    def boundary_faces(self) -> np.ndarray:
        """(k, 3) outward boundary triangles of the elements in use. Found once from the elements,
        then kept by the edits face by face (a cut's new faces become surface, its removed ones
        stop being so)."""
        if self._faces is None:
            from ..mesh import boundary_faces

            self._faces = {tuple(sorted(f)): tuple(f) for f in boundary_faces(self.tets).tolist()}
        if self._face_array is None:        # kept until an edit toggles a face
            self._face_array = np.array(list(self._faces.values()), dtype=np.int64).reshape(-1, 3)
            self._face_array.flags.writeable = False
        return self._face_array

    def _toggle_faces(self, tets: np.ndarray, added: bool) -> None:
        """A face belongs to the boundary when one element has it. An added element's face that
        was boundary is now inside, else it is new surface; a removed element's face that was
        boundary is gone, else its neighbour's side (the reversed face) is now surface."""
        if self._faces is None:
            return
        self._face_array = None
        for face in tets[:, OUTWARD_FACES].reshape(-1, 3).tolist():
            key = tuple(sorted(face))
            if key in self._faces:
                del self._faces[key]
            else:
                self._faces[key] = tuple(face) if added else (face[0], face[2], face[1])

    # ---- material -----------------------------------------------------------------------------

    def set_material(self, material: Material) -> None:
        """Give every element this material (λ, μ and the lumped mass follow): a runtime change,
        read by the next step."""
        m = self.n_elements
        self.material = material
        self._elastic[:m, 1:] = material.lame
        self._density[:m] = material.density
        self._mass[:self.n_nodes] = self._node_mass(np.arange(self.n_nodes))
        self._upload("elastic", "mass")

    # ---- held nodes ---------------------------------------------------------------------------

    def set_held(self, nodes) -> None:
        """Hold exactly these nodes (zero velocity); detached nodes stay detached."""
        nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
        bad = nodes[(nodes < 0) | (nodes >= self.n_nodes)]
        if len(bad):
            raise TissueError(f"fixed: node ids {bad[:10].tolist()} out of range [0, {self.n_nodes})")
        held = self._held[:self.n_nodes]
        held[held == HELD] = 0
        held[nodes[held[nodes] != DETACHED]] = HELD
        self._upload("held")
        for structure in self._alive():
            if hasattr(structure, "held_changed"):
                structure.held_changed()

    @property
    def held_nodes(self) -> np.ndarray:
        return np.flatnonzero(self.held == HELD)

    # ---- topology edits ------------------------------------------------------------------------

    def subscribe(self, structure) -> None:
        """Call `structure.topology_changed(edit)` after each element edit, and
        `structure.held_changed()`, where it has one, after `set_held` (held weakly)."""
        self._subscribers.append(weakref.ref(structure))

    def _alive(self) -> list:
        self._subscribers = [ref for ref in self._subscribers if ref() is not None]
        return [ref() for ref in self._subscribers]

    def _notify(self, edit: Edit) -> None:
        for structure in self._alive():
            structure.topology_changed(edit)

    def add_nodes(self, points) -> np.ndarray:
        """Append nodes at these rest positions (k, 3); returns their ids. They stay detached
        (still) until an element uses them."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(points).all():
            raise TissueError("add_nodes: non-finite coordinates")
        self._reserve(nodes=len(points))
        ids = np.arange(self.n_nodes, self.n_nodes + len(points))
        self._rest[ids] = points
        self._held[ids] = DETACHED
        self._mass[ids] = 0.0
        self._valence[ids] = 0
        self._incidence[ids] = -1
        self.n_nodes += len(points)
        self._flush(nodes=ids)
        return ids

    def add_elements(self, tets, material: Material | None = None) -> np.ndarray:
        """Append positively oriented, non-degenerate tetrahedra (k, 4) over existing nodes, of
        `material` (default: the body's); returns their ids."""
        tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
        material = material or self.material
        bad = np.flatnonzero(((tets < 0) | (tets >= self.n_nodes)).any(axis=1))
        if len(bad):
            raise TissueError(f"add_elements: tetrahedra {bad[:10].tolist()} index nodes out of range "
                              f"[0, {self.n_nodes})")
        X = self._rest
        volumes = signed_volumes(X[:self.n_nodes], tets)
        bad = np.flatnonzero(~(volumes > 0))
        if len(bad):
            raise TissueError(f"add_elements: tetrahedra {bad[:10].tolist()} are inverted or degenerate "
                              f"(signed volumes {volumes[bad[:3]].tolist()})")
        per_node = np.bincount(tets.reshape(-1), minlength=self.n_nodes)
        self._reserve(elements=len(tets), slots=int((self._valence[:self.n_nodes] + per_node).max(initial=0)))
        ids = np.arange(self.n_elements, self.n_elements + len(tets))
        Dm = np.stack([X[tets[:, i]] - X[tets[:, 0]] for i in (1, 2, 3)], axis=2)
        lam, mu = material.lame
        self._tets[ids] = tets
        self._Dm_inv[ids] = np.linalg.inv(Dm)
        self._rest_frame[ids] = edge_frames(X[tets[:, :3]])
        self._elastic[ids] = np.column_stack([volumes, np.full(len(tets), lam), np.full(len(tets), mu)])
        self._density[ids] = material.density
        self.n_elements += len(tets)
        self._toggle_faces(tets, added=True)
        self._flush(elements=ids, nodes=self._link(ids))
        self._notify(Edit(added=ids))
        return ids

    def remove_elements(self, ids) -> np.ndarray:
        """Remove these elements; returns where every previous element went (−1: removed). The
        last elements move into the freed slots, so the rest stay contiguous."""
        ids = np.unique(np.asarray(ids, dtype=np.int64).reshape(-1))
        m = self.n_elements
        if len(ids) and (ids[0] < 0 or ids[-1] >= m):
            raise TissueError(f"remove_elements: ids out of range [0, {m}): {ids[(ids < 0) | (ids >= m)][:10].tolist()}")
        self._toggle_faces(self._tets[ids], added=False)
        keep = np.ones(m, dtype=bool)
        keep[ids] = False
        kept_tail = np.flatnonzero(keep[m - len(ids):]) + m - len(ids)   # survivors that must move
        holes = ids[ids < m - len(ids)]                                   # freed slots they fill
        where = np.where(keep, np.arange(m), -1)
        where[kept_tail] = holes
        # The gather entries of the removed elements' nodes and the moved ones' nodes: removed
        # codes dropped, moved ones renamed, survivors in order.
        touched = np.unique(self._tets[np.concatenate([ids, kept_tail])])
        rows = self._incidence[touched]
        element = np.where(rows >= 0, where[rows // 4], -1)
        gone = element < 0
        order = np.argsort(gone, axis=1, kind="stable")
        self._incidence[touched] = np.take_along_axis(np.where(gone, -1, 4 * element + rows % 4), order, axis=1)
        self._valence[touched] = (~gone).sum(axis=1)
        for name in ("_tets", "_Dm_inv", "_rest_frame", "_elastic", "_density"):
            array = getattr(self, name)
            array[holes] = array[kept_tail]
        self.n_elements = m - len(ids)
        self._relink(touched)
        self._flush(elements=holes, nodes=touched)
        self._notify(Edit(moved_from=kept_tail, moved_to=holes))
        return where

    def _link(self, ids: np.ndarray) -> np.ndarray:
        """Add elements' gather entries (each corner in its node's next free slot); returns the
        nodes touched."""
        if len(ids) == 0:
            return np.zeros(0, dtype=np.int64)
        codes = (4 * ids[:, None] + np.arange(4)).reshape(-1).astype(np.int32)
        nodes = self._tets[ids].reshape(-1)
        order = np.argsort(nodes, kind="stable")
        sorted_nodes = nodes[order]
        first = np.searchsorted(sorted_nodes, sorted_nodes)
        self._incidence[sorted_nodes, self._valence[sorted_nodes] + np.arange(len(order)) - first] = codes[order]
        touched, count = np.unique(sorted_nodes, return_counts=True)
        self._valence[touched] += count
        self._relink(touched)
        return touched

    def _relink(self, touched: np.ndarray) -> None:
        """The mass of nodes whose elements changed; those left without any detached, those
        given one again free."""
        self._mass[touched] = self._node_mass(touched)
        held = self._held
        held[touched[(self._valence[touched] == 0)]] = DETACHED
        held[touched[(self._valence[touched] > 0) & (held[touched] == DETACHED)]] = 0

    def _node_mass(self, nodes: np.ndarray) -> np.ndarray:
        """Σ ρ V / 4 over each node's elements, summed in ascending element order: to the bit
        what a model built fresh on the same elements holds, however many edits came before (an
        edit's ± would leave rounding residue behind)."""
        codes = np.sort(self._incidence[nodes], axis=1)             # −1 (unused slots) first
        elements = np.maximum(codes, 0) // 4
        share = np.where(codes >= 0, self._density[elements] * self._elastic[elements, 0] / 4.0, 0.0)
        return np.cumsum(share, axis=1)[:, -1] if share.shape[1] else np.zeros(len(nodes))

    def _flush(self, elements=(), nodes=()) -> None:
        """Write these elements' and nodes' rows, and the counts, to the device in one launch
        (an edit touches a few rows: uploading whole arrays would cost far more)."""
        e = np.unique(np.asarray(elements, dtype=np.int64))
        v = np.unique(np.asarray(nodes, dtype=np.int64))
        slots = self._incidence.shape[1]
        rows = max(len(e), len(v), 1)
        staging = self._staging
        if staging is None or len(staging[0]) < rows or staging[2].shape[1] != 3 + slots:
            rows = max(rows, 64, 2 * len(staging[0]) if staging is not None else 0)
            staging = self._staging = (np.empty((rows, 5), np.int32), np.empty((rows, 21), self._real),
                                       np.empty((rows, 3 + slots), np.int32), np.empty((rows, 4), self._real))
        element_ints, element_reals, node_ints, node_reals = staging
        element_ints[len(e):, 0] = -1
        element_ints[:len(e), 0] = e
        element_ints[:len(e), 1:] = self._tets[e]
        element_reals[:len(e), :9] = self._Dm_inv[e].reshape(-1, 9)
        element_reals[:len(e), 9:18] = self._rest_frame[e].reshape(-1, 9)
        element_reals[:len(e), 18:] = self._elastic[e]
        node_ints[len(v):, 0] = -1
        node_ints[:len(v), 0] = v
        node_ints[:len(v), 1] = self._held[v]
        node_ints[:len(v), 2] = self._valence[v]
        node_ints[:len(v), 3:] = self._incidence[v]
        node_reals[:len(v), :3] = self._rest[v]
        node_reals[:len(v), 3] = self._mass[v]
        self._counts[:] = self.n_nodes, self.n_elements
        self.edits += 1
        WRITE_ROWS(self.pack, *staging, self._counts)


@ti.kernel
def _write_rows(m: MODEL, element_ints: ti.types.ndarray(), element_reals: ti.types.ndarray(),
                node_ints: ti.types.ndarray(), node_reals: ti.types.ndarray(), counts: ti.types.ndarray()):
    """Rows of an edit: per element (id, tets | Dm⁻¹, rest frame, V λ μ), per node (id, held,
    valence, incidence | rest, mass), a row whose id is −1 being padding; and the counts."""
    ti.loop_config(serialize=True)    # a few rows: the thread pool would cost more
    for r in range(element_ints.shape[0]):
        e = element_ints[r, 0]
        if e >= 0:
            m.tets[e] = ti.Vector([element_ints[r, 1], element_ints[r, 2], element_ints[r, 3], element_ints[r, 4]])
            inverse_edges, frame = ti.Matrix.zero(float, 3, 3), ti.Matrix.zero(float, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                inverse_edges[a, b] = element_reals[r, 3 * a + b]
                frame[a, b] = element_reals[r, 9 + 3 * a + b]
            m.Dm_inv[e] = inverse_edges
            m.rest_frame[e] = frame
            m.elastic[e] = ti.Vector([element_reals[r, 18], element_reals[r, 19], element_reals[r, 20]])
    ti.loop_config(serialize=True)
    for r in range(node_ints.shape[0]):
        v = node_ints[r, 0]
        if v >= 0:
            m.held[v] = node_ints[r, 1]
            m.valence[v] = node_ints[r, 2]
            for k in range(node_ints.shape[1] - 3):
                m.incidence[v, k] = node_ints[r, 3 + k]
            m.rest[v] = ti.Vector([node_reals[r, 0], node_reals[r, 1], node_reals[r, 2]])
            m.mass[v] = node_reals[r, 3]
    ti.loop_config(serialize=True)
    for _ in range(1):
        m.counts[0] = counts[0]
        m.counts[1] = counts[1]


WRITE_ROWS = replayed(_write_rows)
