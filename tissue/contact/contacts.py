"""The contacts of a step: the record detection hands the contact stage (`Contacts`), and the
contact points a body's surface carries (`surface_samples`).

Contact points ("samples") are fixed points of a body's surface triangles, p = Σ uⱼ x[nⱼ]: its
vertices, and optionally its edge midpoints and triangle centroids (`surface_samples`), which keep
obstacles thinner than the mesh spacing (a probe, a rib) from slipping between the vertices (the
paper samples the surfaces with Layered Depth Images for the same reason). A contact is a sample
p, the closest point c on the other surface, the unit normal n (from the other surface toward the
side where p belongs) and the gap g = n·(p - c) (negative when p has penetrated). For soft–soft
contacts c is a point of a triangle of the other body with barycentric weights w, so
g = n·(Σ uⱼ xⱼ - Σ wⱼ yⱼ) is linear in both bodies' nodes.
"""

from dataclasses import dataclass, fields

import numpy as np

from ..errors import TissueError

SAMPLINGS = ("vertices", "edges", "faces")


@dataclass
class Contacts:
    """One row per contact point (all arrays have the same first dimension k)."""

    body: np.ndarray            # (k,) soft body the contact point belongs to
    sample: np.ndarray          # (k,) index of the point among that body's samples (its identity)
    nodes: np.ndarray           # (k, 3) the body's nodes carrying the point (a vertex: v, v, v)
    own_weights: np.ndarray     # (k, 3) its weights on them (a vertex: 1, 0, 0)
    other: np.ndarray           # (k,) obstacle index (rigid) or body index (soft)
    soft: np.ndarray            # (k,) bool: the other side is a soft body
    triangle: np.ndarray        # (k, 3) nodes of the other body's triangle (soft), else -1
    weights: np.ndarray         # (k, 3) barycentric weights of c on that triangle (soft), else 0
    normal: np.ndarray          # (k, 3) unit normal, from the other surface toward the point
    gap: np.ndarray             # (k,) signed distance along the normal (< 0: penetration)
    closest: np.ndarray         # (k, 3) the closest point c on the other surface
    other_motion: np.ndarray    # (k, 3) rigid: displacement of the material point at c over the step
    # (not a field) where detection's read-out launch wrote these contacts (tissue.contact.hits.ReadOut):
    # the row writer reads them there, and keys() their keys, while it holds them (until the next read-out)
    read_out = None

    def __len__(self) -> int:
        return len(self.body)

    @property
    def vertex(self) -> np.ndarray:
        """The node of each contact point that is a vertex (the first carrier node otherwise)."""
        return self.nodes[:, 0]

    @staticmethod
    def empty() -> "Contacts":
        i, f = np.int32, float
        return Contacts(*(np.zeros(s, dtype=d) for s, d in (
            (0, i), (0, i), ((0, 3), i), ((0, 3), f), (0, i), (0, bool), ((0, 3), i), ((0, 3), f),
            ((0, 3), f), (0, f), ((0, 3), f), ((0, 3), f))))

    def take(self, index) -> "Contacts":
        return Contacts(*(getattr(self, f.name)[index] for f in fields(Contacts)))

    def keys(self) -> np.ndarray:
        """An integer identity per contact (body, sample, kind, other), stable across steps."""
        if self.read_out is not None and self.read_out.holds(self):
            return self.read_out.keys[:len(self)].copy()
        return ((self.body.astype(np.int64) << 40) | (self.sample.astype(np.int64) << 12)
                | (self.soft.astype(np.int64) << 11) | self.other.astype(np.int64))


def surface_samples(faces: np.ndarray, sampling: str = "vertices") -> tuple[np.ndarray, np.ndarray]:
    """(nodes (s, 3) int32, weights (s, 3)) of a surface's contact points: its vertices (v, v, v;
    1, 0, 0), then for "edges" and "faces" its edge midpoints, then for "faces" its centroids."""
    if sampling not in SAMPLINGS:
        raise TissueError(f"sampling: unknown {sampling!r}; expected one of {SAMPLINGS}")
    v = np.unique(faces)
    nodes, weights = [np.repeat(v[:, None], 3, axis=1)], [np.tile([1.0, 0.0, 0.0], (len(v), 1))]
    if sampling in ("edges", "faces"):
        e = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
        nodes.append(e[:, [0, 1, 1]])
        weights.append(np.tile([0.5, 0.5, 0.0], (len(e), 1)))
    if sampling == "faces":
        nodes.append(faces)
        weights.append(np.full((len(faces), 3), 1.0 / 3.0))
    return np.concatenate(nodes).astype(np.int32), np.concatenate(weights)
