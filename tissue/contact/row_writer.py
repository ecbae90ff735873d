"""The constraint rows of a step's contacts and each touched body's JDS, written by one replayed
launch (tissue.launch): what `constraints.jacobian`, `with_free_values` and `JaggedDiagonal` build
in numpy (their definitions: constraints.py), the same numbers bit for bit, in the same order.

Contacts only: a stage with attachments or instruments' jaws builds its rows in numpy (their rows
are few; `ContactStage._rows`). One launch instead of some forty numpy calls, and nothing of a
step's rows can be kept from the step before while the bodies move.

The launch reads the contacts from two buffers (`ints`: body, other, soft, frictionless, the
carrier nodes, the other triangle; `reals`: the weights on both, the normal, the gap, the
obstacle's motion): those detection's read-out wrote them into (tissue.contact.hits: its columns
are these, and more), or filled by a handful of numpy copies for contacts from elsewhere; and the
bodies' free and start positions from the detection's state (all bodies in one array,
tissue.contact.detection). It writes, in buffers kept by capacity: the entries (block row, body,
node) and their 3×3 values, δ_free, the frames and row directions, and per body its JDS: [perm |
count | jd_ptr | node | local | touched] (int32, as `JaggedDiagonal.packed`), the entries' values
in the backend's float type and their block rows. All in one serial loop: a few hundred
contacts, where a parallel loop's dispatch would cost more.

Every number is the numpy builders', bit for bit: Taichi's CPU code contracts no multiply-add and
divides as numpy does (entry by entry), and the three-term sums are added in einsum's order
(`_added`), which Taichi's fast math would reorder were it not kept by a product with a runtime 1.
"""

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..launch import replayed
from .constraints import AXIS_CROSS, ConstraintRows, JaggedDiagonal
from .contacts import Contacts
from .storage import Storage

# ints columns, reals columns of a contact
BODY, OTHER, SOFT, FRICTIONLESS, NODES, TRIANGLE = 0, 1, 2, 3, 4, 7
OWN_WEIGHTS, WEIGHTS, NORMAL, GAP, MOTION = 0, 3, 6, 9, 10
N_INTS, N_REALS = 10, 13
# per body in `counts` (after the entries' count): n_active, jagged diagonals, nnz, touched nodes,
# where its packed ints start, where its values (and rows) start
PER_BODY = 6
_AXIS_CROSS = AXIS_CROSS.tolist()      # (the kernel's constants)
# A body's blocks in a contact's block row: its carrier nodes' (at most 3), or the other
# triangle's (3); never both: a soft contact of a body with itself is refused (RowWriter.write).
MAX_BLOCKS = 3


@ti.func
def _carried(state: ti.template(), ints: ti.template(), reals: ti.template(), c, nodes: ti.template(),
             weights: ti.template(), first, i, zero_one: ti.template()):
    """Coordinate i of the step's displacement (free − start) of contact c's point Σⱼ wⱼ xⱼ on the
    nodes in its `nodes` columns at the weights in its `weights` columns, of the body whose state
    rows start at `first` (einsum "kj,kjc->kc": in order)."""
    return _added(reals[c, weights] * _moved(state, first + ints[c, nodes], i),
                  reals[c, weights + 1] * _moved(state, first + ints[c, nodes + 1], i),
                  reals[c, weights + 2] * _moved(state, first + ints[c, nodes + 2], i), zero_one)


@ti.func
def _moved(state: ti.template(), at, i):
    """Coordinate i of a node's displacement over the step (free − start; state row `at`)."""
    return state[at, i] - state[at, 3 + i]


@ti.func
def _added(a, b, c, zero_one: ti.template()):
    """a + b + c as numpy's einsum adds three terms: onto a zero (which makes a sum of zeros +0),
    one after another, in the caller's order (einsum adds the products of two contiguous rows,
    "ki,ki->k" and "kij,kj->ki", in two SIMD lanes: x0 + x2, then x1; strided ones, "kj,kjc->kc",
    in order). zero_one: [0.0, 1.0] read at run time: Taichi's fast math would drop a literal
    zero and reorder the sum, not a product with a number it does not know."""
    one = zero_one[1]
    return (((zero_one[0] + a) * one + b) * one + c) * one


@ti.func
def _dot(u, v, zero_one: ti.template()):
    """einsum's u · v of two contiguous rows (see _added)."""
    return _added(u[0] * v[0], u[2] * v[2], u[1] * v[1], zero_one)


@ti.func
def _divided(v, s):
    """v / s entry by entry (a vector divided by a scalar is multiplied by its reciprocal)."""
    return ti.Vector([v[0] / s, v[1] / s, v[2] / s])


@ti.func
def _frame(n, zero_one: ti.template()):
    """constraints.tangent_frames of one normal: rows n, t1, t2 (t1 = n × the world axis least
    aligned with n, as the product with AXIS_CROSS[axis] that it is there)."""
    n = _divided(n, ti.sqrt(_dot(n, n, zero_one)))
    axis = 0
    if ti.abs(n[1]) < ti.abs(n[axis]):
        axis = 1
    if ti.abs(n[2]) < ti.abs(n[axis]):
        axis = 2
    t1 = ti.Vector([0.0, 0.0, 0.0], ti.f64)
    for i in ti.static(range(3)):
        for a in ti.static(range(3)):
            if axis == a:
                t1[i] = _dot(ti.Vector(_AXIS_CROSS[a][i], ti.f64), n, zero_one)
    t1 = _divided(t1, ti.sqrt(_dot(t1, t1, zero_one)))
    t2 = ti.Vector([n[1] * t1[2] - n[2] * t1[1], n[2] * t1[0] - n[0] * t1[2], n[0] * t1[1] - n[1] * t1[0]])
    return ti.Matrix.rows([n, t1, t2])


@ti.kernel
def _write_rows(sizes: ti.types.ndarray(), ints: ti.types.ndarray(), reals: ti.types.ndarray(),
                state: ti.types.ndarray(), block: ti.types.ndarray(), body: ti.types.ndarray(),
                node: ti.types.ndarray(), value: ti.types.ndarray(), q: ti.types.ndarray(),
                frames: ti.types.ndarray(), directions: ti.types.ndarray(), packed: ti.types.ndarray(),
                jds_value: ti.types.ndarray(), jds_row: ti.types.ndarray(), counts: ti.types.ndarray(),
                per_row: ti.types.ndarray(), present: ti.types.ndarray(), zero_one: ti.types.ndarray()):
    """sizes: [contacts, bodies, each body's first row in `state`, and the end]. counts: the
    entries, then PER_BODY numbers a body. per_row (contacts, 3) and present (state's rows, zero
    between launches): scratch. zero_one: [0.0, 1.0] (_added)."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        k, n_bodies = sizes[0], sizes[1]
        n_own = 0
        for c in range(k):
            for j in range(3):
                if reals[c, OWN_WEIGHTS + j] != 0.0:
                    n_own += 1
        e_own, e_soft = 0, n_own
        for c in range(k):
            F = _frame(ti.Vector([reals[c, NORMAL], reals[c, NORMAL + 1], reals[c, NORMAL + 2]]), zero_one)
            D = F
            if ints[c, FRICTIONLESS] != 0:          # (as numpy's product with 0: the zeros' signs)
                for i in ti.static(range(3)):
                    D[1, i], D[2, i] = F[1, i] * 0.0, F[2, i] * 0.0
            for r, i in ti.static(ti.ndrange(3, 3)):
                frames[c, r, i] = F[r, i]
                directions[c, r, i] = D[r, i]
            # δ_free (constraints.with_free_values): the gap, and the tangents on the relative
            # displacement of the two material points
            own, first = ints[c, BODY], sizes[2 + ints[c, BODY]]
            disp = ti.Vector([-reals[c, MOTION], -reals[c, MOTION + 1], -reals[c, MOTION + 2]])
            for i in ti.static(range(3)):
                disp[i] = disp[i] + _carried(state, ints, reals, c, NODES, OWN_WEIGHTS, first, i, zero_one)
            if ints[c, SOFT] != 0:
                other = sizes[2 + ints[c, OTHER]]
                for i in ti.static(range(3)):
                    disp[i] = disp[i] - _carried(state, ints, reals, c, TRIANGLE, WEIGHTS, other, i, zero_one)
            q[3 * c] = reals[c, GAP]
            for r in ti.static(range(1, 3)):
                q[3 * c + r] = _dot(ti.Vector([D[r, 0], D[r, 1], D[r, 2]]), disp, zero_one)
            # H's blocks: the point's own (weights 0 left out), then the other triangle's -w d
            for j in range(3):
                w = reals[c, OWN_WEIGHTS + j]
                if w != 0.0:
                    block[e_own], body[e_own], node[e_own] = c, own, ints[c, NODES + j]
                    for r, i in ti.static(ti.ndrange(3, 3)):
                        value[e_own, r, i] = w * D[r, i]
                    e_own += 1
            if ints[c, SOFT] != 0:
                for j in range(3):
                    w = -reals[c, WEIGHTS + j]
                    block[e_soft], body[e_soft], node[e_soft] = c, ints[c, OTHER], ints[c, TRIANGLE + j]
                    for r, i in ti.static(ti.ndrange(3, 3)):
                        value[e_soft, r, i] = w * D[r, i]
                    e_soft += 1
        counts[0] = e_soft
        start, value_start = 0, 0
        for b in range(n_bodies):
            start, value_start = _body_jds(b, k, e_soft, start, value_start, sizes, block, body, node, value,
                                           packed, jds_value, jds_row, counts, per_row, present)


@ti.func
def _body_jds(b, k, n_entries, start, value_start, sizes: ti.template(), block: ti.template(), body: ti.template(),
              node: ti.template(), value: ti.template(), packed: ti.template(), jds_value: ti.template(),
              jds_row: ti.template(), counts: ti.template(), per_row: ti.template(), present: ti.template()):
    """Body b's JDS (JaggedDiagonal): its block rows sorted by their number of blocks, descending,
    stably (a counting sort: at most MAX_BLOCKS), and its entries jagged diagonal by jagged
    diagonal; packed from `start`, values and rows from `value_start`. Returns where the next
    body's packed ints and values start."""
    for c in range(k):
        per_row[c, 0], per_row[c, 2] = 0, 0         # its blocks, and those placed so far
    nnz = 0
    for e in range(n_entries):
        if body[e] == b:
            per_row[block[e], 0] += 1
            nnz += 1
    n_active = 0
    for m in range(MAX_BLOCKS):
        for c in range(k):
            if per_row[c, 0] == MAX_BLOCKS - m:
                per_row[c, 1] = n_active            # its sorted position
                packed[start + n_active] = c
                n_active += 1
    for i in range(n_active):
        packed[start + n_active + i] = per_row[packed[start + i], 0]
    n_diagonals = 0
    if n_active > 0:
        n_diagonals = packed[start + n_active]
    # jd_ptr[d]: the entries of rank below d, one per block row with more than d blocks
    o_ptr = start + 2 * n_active
    packed[o_ptr] = 0
    for d in range(n_diagonals):
        longer = 0
        for i in range(n_active):
            if packed[start + n_active + i] > d:
                longer += 1
        packed[o_ptr + d + 1] = packed[o_ptr + d] + longer
    o_node = o_ptr + n_diagonals + 1
    o_local = o_node + nnz
    first = sizes[2 + b]
    for e in range(n_entries):
        if body[e] == b:
            c = block[e]
            at = packed[o_ptr + per_row[c, 2]] + per_row[c, 1]
            per_row[c, 2] += 1
            packed[o_node + at] = node[e]
            jds_row[value_start + at] = c
            for r, i in ti.static(ti.ndrange(3, 3)):
                jds_value[value_start + at, r, i] = ti.cast(value[e, r, i], float)     # (the backend's type)
            present[first + node[e]] = 1
    # The nodes touched, in order, and each entry's index among them
    o_touched = o_local + nnz
    n_touched = 0
    for v in range(sizes[3 + b] - first):
        if present[first + v] != 0:
            packed[o_touched + n_touched] = v
            n_touched += 1
            present[first + v] = n_touched
    for e in range(nnz):
        packed[o_local + e] = present[first + packed[o_node + e]] - 1
    for t in range(n_touched):
        present[first + packed[o_touched + t]] = 0
    at = 1 + PER_BODY * b
    counts[at], counts[at + 1], counts[at + 2], counts[at + 3] = n_active, n_diagonals, nnz, n_touched
    counts[at + 4], counts[at + 5] = start, value_start
    return o_touched + n_touched, value_start + nnz


_write_rows_replayed = replayed(_write_rows)


class RowWriter:
    """A contact stage's rows written by `_write_rows` into arrays kept between steps: two sets,
    alternating from build to build, so that a build leaves the rows the stage kept before it
    (which the factors' `before` and the warm start read) as they were."""

    def __init__(self):
        self._sets = [Storage(numpy=True), Storage(numpy=True)]
        self._which = 0
        self._args = [(None, 0), (None, 0)]     # per set: the launch's arguments, and for how many contacts

    def write(self, contacts: Contacts, frictionless: np.ndarray, state: np.ndarray, state_offset: np.ndarray
              ) -> tuple[ConstraintRows, dict[int, JaggedDiagonal]]:
        """The rows of `contacts` with δ_free, and the JDS of each body they touch (ordered by body).
        frictionless: (k,) bool; state: every body's free and start positions (n, 6), body b's
        from row state_offset[b]. The rows' and the JDS' arrays are views of this writer's
        buffers, which the second build after this one overwrites (copy them to keep them)."""
        if contacts.soft.any() and (contacts.soft & (contacts.other == contacts.body)).any():
            raise TissueError("row writer: a soft contact of a body with itself (more blocks than a "
                              "block row holds)")
        self._which = 1 - self._which
        k = len(contacts)
        args = self._arguments(k, state, len(state_offset) - 1)
        sizes, ints, reals = args[:3]
        sizes[0], sizes[2:] = k, state_offset
        read_out = contacts.read_out
        if read_out is not None and read_out.holds(contacts):      # (its columns are ours: tissue.contact.hits)
            ints, reals = read_out.ints, read_out.reals
            args = (sizes, ints, reals, *args[3:])
        else:
            ints[:k, BODY], ints[:k, OTHER], ints[:k, SOFT] = contacts.body, contacts.other, contacts.soft
            ints[:k, NODES:NODES + 3], ints[:k, TRIANGLE:TRIANGLE + 3] = contacts.nodes, contacts.triangle
            reals[:k, OWN_WEIGHTS:OWN_WEIGHTS + 3] = contacts.own_weights
            reals[:k, WEIGHTS:WEIGHTS + 3], reals[:k, NORMAL:NORMAL + 3], reals[:k, GAP] = \
                contacts.weights, contacts.normal, contacts.gap
        ints[:k, FRICTIONLESS], reals[:k, MOTION:MOTION + 3] = frictionless, contacts.other_motion
        _write_rows_replayed(*args)
        block, body, node, value, q, frames, directions, packed, jds_value, jds_row, counts = args[4:15]
        counts = counts.tolist()
        n = counts[0]
        rows = ConstraintRows(n_rows=3 * k, n_contacts=k, block=block[:n], body=body[:n], node=node[:n],
                              value=value[:n], q=q[:3 * k], frames=frames[:k], directions=directions[:k])
        jds = {}
        for b in range(len(state_offset) - 1):
            n_active, n_diagonals, nnz, n_touched, start, at = counts[1 + PER_BODY * b:1 + PER_BODY * (b + 1)]
            if nnz:
                jds[b] = JaggedDiagonal.from_packed(packed[start:], jds_value[at:at + nnz], jds_row[at:at + nnz],
                                                    n_active, n_diagonals, n_touched)
        return rows, jds

    def _arguments(self, k: int, state: np.ndarray, n_bodies: int) -> tuple:
        """The launch's arguments in the current set: kept while they have room for k contacts
        and read the same state for as many bodies (whole buffers, the same objects: the launch
        replays). Rebuilt ones take room for twice the last (or k): each rebuild records the launch
        anew, so a press whose contacts grow step by step rebuilds them a few times, not at each new
        largest k (the storage's arrays may then double once more than k needs)."""
        args, room = self._args[self._which]
        if args is not None and k <= room and args[3] is state and len(args[0]) == n_bodies + 3:
            return args
        room = max(k, 2 * room)
        s, i32, f64 = self._sets[self._which], ti.i32, ti.f64
        e = 6 * room                          # entries: at most 3 on the point's body, 3 on the other's
        sizes = s.get("sizes", n_bodies + 3, i32)[:n_bodies + 3]
        sizes[1] = n_bodies
        args = (sizes, s.get("ints", room, i32, (N_INTS,)), s.get("reals", room, f64, (N_REALS,)), state,
                s.get("block", e, i32), s.get("body", e, i32), s.get("node", e, i32), s.get("value", e, f64, (3, 3)),
                s.get("q", 3 * room, f64), s.get("frames", room, f64, (3, 3)), s.get("directions", room, f64, (3, 3)),
                # per body: perm, count (a block row each), jd_ptr (MAX_BLOCKS + 1), node, local, touched
                s.get("packed", n_bodies * (2 * room + MAX_BLOCKS + 1) + 3 * e, i32),
                s.get("jds_value", e, backend.current().real, (3, 3)), s.get("jds_row", e, i32),
                s.get("counts", 1 + PER_BODY * n_bodies, i32), s.get("per_row", room, i32, (3,)),
                s.get("present", len(state), i32), s.get("zero_one", 2, f64))
        args[-1][:2] = 0.0, 1.0
        self._args[self._which] = (args, room)
        return args
