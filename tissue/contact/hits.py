"""What detection found: every soft body's hits in one buffer that the detection launches write
(tissue.contact.detection), and their reading as the step's Contacts.
"""

import numpy as np

from .contacts import Contacts


class HitBuffer:
    """Every body's detection output in one buffer, body after body: a row per sample, then one
    row where a soft launch leaves the room its triangle grid needed (gap[-1]), each row a slot
    per obstacle and per other body: its gap in `gap` (1e300: none), a hit's other 10 numbers in
    `array` (normal (3), closest point (3), weights on the other body's triangle (3) and its id
    (1), on an obstacle 0, 0, 0, -1; apart, so that finding the hits reads 8 bytes a slot, not
    the records' cache lines); and what identifies a hit in each row and slot, so that the hits of
    every body are read at once (a step's few dozen numpy calls once, not once per body and then
    joined)."""

    def __init__(self, samples, faces, n_obstacles: int, soft_soft: bool, npr):
        n_bodies = len(samples)
        self.n_obstacles = n_obstacles
        slots = max(n_obstacles + (n_bodies - 1 if soft_soft else 0), 1)
        rows = [len(nodes) + 1 for nodes, _ in samples]
        start = np.r_[0, np.cumsum(rows)]
        self.gap = np.full((start[-1], slots), 1e300, npr)     # (in float32: inf)
        self.array = np.zeros((start[-1], slots, 10), npr)
        self.outs = [(self.gap[start[b]:start[b + 1]], self.array[start[b]:start[b + 1]]) for b in range(n_bodies)]
        self.room_rows = start[1:] - 1
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
        self.faces = np.concatenate(faces)
        self.face_offset = np.r_[0, np.cumsum([len(f) for f in faces])]
        self.kept = None                          # the last hits without soft ones (_rigid_identities)

    def contacts(self, poses, previous_poses, moving) -> Contacts:
        """Every body's hits as Contacts, ordered by (body, sample, kind, other) (np.nonzero's
        order over the buffer). poses / previous_poses: per obstacle (R, t) at the end of the step
        and at its start; moving: the obstacles that move (the others' points do not)."""
        # (none: 1e300, or inf in float32; np.nonzero over the 2-d mask costs twice this)
        hit = self.gap < 1e299
        hit[self.room_rows] = False
        row, slot = np.divmod(hit.ravel().nonzero()[0], self.gap.shape[1])
        res = self.array[row, slot].astype(np.float64, copy=False)
        soft = slot >= self.n_obstacles
        if soft.any():
            hits = self._identities(row, slot, soft)
            face = res[soft, 9].astype(np.int64)
            hits["triangle"][soft] = self.faces[self.face_offset[hits["other"][soft]] + face]
            hits["weights"] = np.where(soft[:, None], res[:, 6:9], 0.0)
        else:
            hits = self._rigid_identities(row, slot, soft)
        point = res[:, 3:6]
        # The material point of the obstacle now at `point` was, one step earlier, at
        # R0 R1ᵀ (point - t1) + t0.
        motion = np.zeros((len(row), 3))
        for j in moving:                        # (slot j < n_obstacles: obstacle j)
            sel = slot == j
            if sel.any():
                (R1, t1), (R0, t0) = poses[j], previous_poses[j]
                p = point[sel]
                motion[sel] = p - ((p - t1) @ R1 @ R0.T + t0)
        return Contacts(**hits, normal=res[:, :3], gap=self.gap[row, slot].astype(np.float64, copy=False),
                        closest=point, other_motion=motion)

    def _identities(self, row, slot, soft) -> dict:
        """What identifies the hits in the buffer's rows `row` and slots `slot`: their Contacts
        fields body, sample, nodes, own_weights, other, soft, triangle and weights (those of a hit
        on an obstacle)."""
        k = len(row)
        body = self.body[row]
        return dict(body=body, sample=self.sample[row], nodes=self.nodes[row],
                    own_weights=self.weights[row].astype(np.float64, copy=False), other=self.other[body, slot],
                    soft=soft, triangle=np.full((k, 3), -1, np.int32), weights=np.zeros((k, 3)))

    def _rigid_identities(self, row, slot, soft) -> dict:
        """`_identities` of hits on obstacles alone: last step's arrays when the hits are the same
        (a body at rest; the arrays are never written after), so that the contact stage finds
        them the same at once."""
        kept = self.kept
        if kept is not None and kept[0].tobytes() == row.tobytes() and kept[1].tobytes() == slot.tobytes():
            return dict(kept[2])
        hits = self._identities(row, slot, soft)
        self.kept = (row, slot, hits)
        return dict(hits)
