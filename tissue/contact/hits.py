"""What detection found: every soft body's hits in one buffer that the detection launches write
(tissue.contact.detection), and their reading as the step's Contacts by one replayed launch
(`_read_hits`): the hits in np.nonzero's order over the buffer, their identities, numbers and
keys written into buffers in the row writer's columns (tissue.contact.row_writer), which reads
them there; the host copies the Contacts' arrays out of them and adds the obstacles' motion.
"""

import numpy as np
import taichi as ti

from ..launch import replayed
from .contacts import Contacts
from .row_writer import BODY, GAP, N_INTS, N_REALS, NODES, NORMAL, OTHER, OWN_WEIGHTS, SOFT, TRIANGLE, WEIGHTS

# The read-out's columns past the row writer's: the hit's sample, and its row and slot in the buffer
SAMPLE, ROW, SLOT = N_INTS, N_INTS + 1, N_INTS + 2
CLOSEST = N_REALS


@ti.kernel
def _read_hits(gap: ti.types.ndarray(), array: ti.types.ndarray(), body: ti.types.ndarray(),
               sample: ti.types.ndarray(), nodes: ti.types.ndarray(), weights: ti.types.ndarray(),
               other: ti.types.ndarray(), faces: ti.types.ndarray(), face_offset: ti.types.ndarray(),
               n_obstacles: ti.i32, ints: ti.types.ndarray(), reals: ti.types.ndarray(), keys: ti.types.ndarray(),
               counts: ti.types.ndarray()):
    """The hits of the buffer (gap < 1e299; each body's last row, the room its soft launch needed,
    left out), row after row and slot after slot, into ints, reals and keys (the module's
    columns). counts: [hits, 1 when they are on obstacles alone and in the rows and slots of the
    last launch's (counts[0] before it) hits, else 0]."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        n_rows, n_slots, before = gap.shape[0], gap.shape[1], counts[0]
        k, same = 0, 1
        for r in range(n_rows):
            if r + 1 < n_rows and body[r + 1] == body[r]:          # (not its body's last row)
                for s in range(n_slots):
                    if gap[r, s] < 1e299:
                        b, o, soft = body[r], other[body[r], s], ti.cast(s >= n_obstacles, ti.i32)
                        if k >= before or ints[k, ROW] != r or ints[k, SLOT] != s or soft != 0:
                            same = 0
                        ints[k, BODY], ints[k, OTHER], ints[k, SOFT], ints[k, SAMPLE] = b, o, soft, sample[r]
                        ints[k, ROW], ints[k, SLOT] = r, s
                        face = ti.cast(array[r, s, 9], ti.i32)
                        for j in ti.static(range(3)):
                            ints[k, NODES + j] = nodes[r, j]
                            reals[k, OWN_WEIGHTS + j] = ti.cast(weights[r, j], ti.f64)
                            ints[k, TRIANGLE + j] = -1
                            reals[k, WEIGHTS + j] = 0.0
                            if soft != 0:
                                ints[k, TRIANGLE + j] = faces[face_offset[o] + face, j]
                                reals[k, WEIGHTS + j] = ti.cast(array[r, s, 6 + j], ti.f64)
                            reals[k, NORMAL + j] = ti.cast(array[r, s, j], ti.f64)
                            reals[k, CLOSEST + j] = ti.cast(array[r, s, 3 + j], ti.f64)
                        reals[k, GAP] = ti.cast(gap[r, s], ti.f64)
                        keys[k] = (ti.cast(b, ti.i64) << 40) | (ti.cast(sample[r], ti.i64) << 12) \
                            | (ti.cast(soft, ti.i64) << 11) | ti.cast(o, ti.i64)
                        k += 1
        counts[0], counts[1] = k, same * ti.cast(k == before, ti.i32)


_read_hits_replayed = replayed(_read_hits)


class ReadOut:
    """Where `_read_hits` writes: ints (BODY, OTHER, SOFT, the row writer's FRICTIONLESS, NODES,
    TRIANGLE, SAMPLE, ROW, SLOT), reals (OWN_WEIGHTS, WEIGHTS, NORMAL, GAP, the row writer's
    MOTION, CLOSEST) and keys, a row per hit (room for every slot of the buffer: no growth), and
    counts; `contacts`, the record read from them last (which they hold until the next launch)."""

    def __init__(self, capacity: int):
        self.ints = np.zeros((capacity, SLOT + 1), np.int32)
        self.reals = np.zeros((capacity, CLOSEST + 3), np.float64)
        self.keys = np.zeros(capacity, np.int64)
        self.counts = np.zeros(2, np.int32)
        self.contacts = None

    def holds(self, contacts: Contacts) -> bool:
        return contacts is self.contacts


class HitBuffer:
    """Every body's detection output in one buffer, body after body: a row per sample, then one
    row where a soft launch leaves the room its triangle grid needed (gap[-1]), each row a slot
    per obstacle and per other body: its gap in `gap` (`no_hit`: none), a hit's other 10 numbers in
    `array` (normal (3), closest point (3), weights on the other body's triangle (3) and its id
    (1), on an obstacle 0, 0, 0, -1; apart, so that finding the hits reads 8 bytes a slot, not
    the records' cache lines); and what identifies a hit in each row and slot, so that the hits of
    every body are read at once (one launch, not one per body)."""

    def __init__(self, samples, faces, n_obstacles: int, soft_soft: bool, npr):
        n_bodies = len(samples)
        self.n_obstacles = n_obstacles
        slots = max(n_obstacles + (n_bodies - 1 if soft_soft else 0), 1)
        rows = [len(nodes) + 1 for nodes, _ in samples]
        start = np.r_[0, np.cumsum(rows)]
        # No hit: 1e300, as the detection kernels write it (in float32 that is inf)
        self.no_hit = np.dtype(npr).type(1e300 if np.dtype(npr) == np.float64 else np.inf)
        self.gap = np.full((start[-1], slots), self.no_hit, npr)
        self.array = np.zeros((start[-1], slots, 10), npr)
        self.outs = [(self.gap[start[b]:start[b + 1]], self.array[start[b]:start[b + 1]]) for b in range(n_bodies)]
        self.body = np.repeat(np.arange(n_bodies, dtype=np.int32), rows)
        self.sample = np.concatenate([np.arange(n, dtype=np.int32) for n in rows])
        self.nodes = np.concatenate([np.r_[nodes, np.zeros((1, 3), np.int32)] for nodes, _ in samples])
        self.weights = np.concatenate([np.r_[weights, np.zeros((1, 3), npr)] for _, weights in samples])
        # What each slot of each body's rows touches: obstacle `slot`, or past the obstacles the
        # other bodies in order; their triangles side by side (body b's from face_offset[b]).
        self.other = np.tile(np.arange(slots, dtype=np.int32), (n_bodies, 1))
        for a in range(n_bodies):
            others = [b for b in range(n_bodies) if b != a] if soft_soft else []
            self.other[a, n_obstacles:n_obstacles + len(others)] = others
        self.faces = np.concatenate([*faces, np.zeros((1, 3), np.int32)]).astype(np.int32)   # (a row more: never empty)
        self.face_offset = np.r_[0, np.cumsum([len(f) for f in faces])].astype(np.int32)
        self.read_out = ReadOut(self.gap.size)
        self.kept = None                          # the last hits' identities, on obstacles alone (_identities)

    def contacts(self, poses, previous_poses, moving) -> Contacts:
        """Every body's hits as Contacts, ordered by (body, sample, kind, other) (np.nonzero's
        order over the buffer). poses / previous_poses: per obstacle (R, t) at the end of the step
        and at its start; moving: the obstacles that move (the others' points do not)."""
        out = self.read_out
        _read_hits_replayed(self.gap, self.array, self.body, self.sample, self.nodes, self.weights, self.other,
                            self.faces, self.face_offset, self.n_obstacles, out.ints, out.reals, out.keys, out.counts)
        k, same = out.counts.tolist()
        # The record's arrays: views of a copy of the hits' rows (one numpy call, not one a field)
        ints, reals = out.ints[:k].copy(), out.reals[:k].copy()
        hits = self._identities(ints, reals, same)
        point = reals[:, CLOSEST:CLOSEST + 3]
        # The material point of the obstacle now at `point` was, one step earlier, at
        # R0 R1ᵀ (point - t1) + t0.
        motion = np.zeros((k, 3))
        if moving:
            slot = ints[:, SLOT]
            for j in moving:                        # (slot j < n_obstacles: obstacle j)
                sel = slot == j
                if sel.any():
                    (R1, t1), (R0, t0) = poses[j], previous_poses[j]
                    p = point[sel]
                    motion[sel] = p - ((p - t1) @ R1 @ R0.T + t0)
        out.contacts = Contacts(**hits, normal=reals[:, NORMAL:NORMAL + 3], gap=reals[:, GAP], closest=point,
                                other_motion=motion)
        out.contacts.read_out = out
        return out.contacts

    def _identities(self, ints, reals, same: int) -> dict:
        """The Contacts fields body, sample, nodes, own_weights, other, soft, triangle and weights
        of the hits read out (views of `ints` and `reals`, the hits' rows copied out of the
        read-out's buffers): the last launch's arrays when `same` (the hits are on obstacles
        alone, in the same rows and slots as then: a body at rest; the arrays are never written
        after), so that the contact stage finds them the same at once."""
        if same and self.kept is not None:
            return dict(self.kept)
        soft = ints[:, SOFT] != 0
        hits = dict(body=ints[:, BODY], sample=ints[:, SAMPLE], nodes=ints[:, NODES:NODES + 3],
                    own_weights=reals[:, OWN_WEIGHTS:OWN_WEIGHTS + 3], other=ints[:, OTHER], soft=soft,
                    triangle=ints[:, TRIANGLE:TRIANGLE + 3], weights=reals[:, WEIGHTS:WEIGHTS + 3])
        self.kept = None if soft.any() else hits
        return dict(hits)
