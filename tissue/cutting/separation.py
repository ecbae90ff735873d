"""Separating the two sides of a cut: nodes on cut faces are duplicated, one copy per side.

A cut leaves *cut faces*: interior faces that lie on the cut surface between elements on its two
sides. Around a node on such faces, the incident elements fall into groups that still hold
together through faces that are not cut (union-find over shared faces). One group keeps the node;
each other group gets a copy of it. A node on the crack front (where the cut ends inside the body)
has its elements joined around the front, one group, so it is not duplicated: the crack opens
behind the front and nowhere else. A cut face stays pending until its two elements no longer share
it (then it is a boundary face on each side).
"""

from __future__ import annotations

import numpy as np

from ..mesh.topology import OUTWARD_FACES


def face_key(nodes) -> tuple[int, int, int]:
    a, b, c = sorted(int(n) for n in nodes)
    return a, b, c


def incident_elements(model, nodes) -> np.ndarray:
    """The elements that use this node (or these nodes: once per node using one), from the model's
    gather index."""
    codes = model.incidence_rows[nodes]
    return codes[codes >= 0] // 4


def sharing(model, nodes) -> np.ndarray:
    """The elements that use all of these nodes."""
    common = incident_elements(model, nodes[0])
    for n in nodes[1:]:
        common = np.intersect1d(common, incident_elements(model, n))
    return common


def still_interior(model, faces) -> set:
    """The faces (keys) still shared by two elements."""
    return {f for f in faces if len(sharing(model, f)) == 2}


def duplications(model, pending: set) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which elements take copies of which nodes. Returns (elements (k,) to re-index, their new
    tetrahedra (k, 4) in which a copy of node u is written as −1 − (its index in `sources`), the
    node each copy duplicates (d,))."""
    nodes = sorted({n for f in pending for n in f})
    changed: dict[int, np.ndarray] = {}
    sources: list[int] = []
    for u in nodes:
        elements = incident_elements(model, u)
        if len(elements) < 2:
            continue
        parent = {int(e): int(e) for e in elements}

        def root(e):
            while parent[e] != e:
                parent[e] = parent[parent[e]]
                e = parent[e]
            return e

        owner: dict[tuple, int] = {}
        for e in elements.tolist():
            for face in model.tets[e][OUTWARD_FACES].tolist():
                if u not in face:
                    continue
                key = tuple(sorted(face))          # (face_key of Python ints)
                if key in pending:
                    continue
                if key in owner:
                    parent[root(e)] = root(owner[key])
                else:
                    owner[key] = e
        groups: dict[int, list[int]] = {}
        for e in elements.tolist():
            groups.setdefault(root(e), []).append(e)
        for group in sorted(groups.values(), key=min)[1:]:
            copy = -1 - len(sources)
            sources.append(u)
            for e in group:
                tet = changed.setdefault(e, model.tets[e].astype(np.int64).copy())
                tet[tet == u] = copy
    elements = np.array(sorted(changed), dtype=np.int64)
    tets = np.array([changed[e] for e in elements], dtype=np.int64).reshape(-1, 4)
    return elements, tets, np.array(sources, dtype=np.int64)
