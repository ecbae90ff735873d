"""One cut step: the swept surface → the elements it crosses → their split (tissue.cutting.subdivision,
with the quality bound) → the two sides separated (tissue.cutting.separation) → the model's edits
(FEM data, mass, gather index, boundary, held nodes and the solver follow them) → the new nodes'
state → the compliance's low-rank update. Each step reports what it created, the worst quality,
and its time by stage.

The geometry is found in the current (deformed) configuration, where the blade is: a cut point at
fraction t of an edge is at that fraction of the edge in the rest shape too (the element's map is
affine), and its position and velocity are interpolated alike. Quality is measured in the rest
shape (what the stiffness sees). The swept surface is kept where the blade swept it (world
coordinates): material that moves far while a cut is under way is judged against where the blade
was, so a slow cut through a swinging body may leave an element bridging the two sides.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .. import backend
from ..errors import TissueError
from ..fem.model import HELD
from . import subdivision
from .separation import duplications, face_key, incident_elements, sharing, still_interior
from .subdivision import SNAP, quality, split_element, within_bound
from .surface import CutSurface

_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TRIPLES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])        # face opposite corner i


@dataclass
class CutReport:
    """What one cut step did. Quality: of the elements it created (inf / 1 when none)."""

    split: int = 0                  # elements split
    created: int = 0                # elements created by splitting
    nodes_added: int = 0            # cut points and copies of nodes on the cut
    snapped: int = 0                # nodes snapped onto the cut
    separated: int = 0              # nodes duplicated to separate the sides
    min_dihedral: float = float("inf")
    max_condition: float = 1.0
    seconds: dict = field(default_factory=dict)  # geometry, model, state, compliance


@dataclass
class _Plan:
    elements: np.ndarray            # elements split
    sub_tets: np.ndarray            # their pieces (new cut points numbered from n_nodes)
    cut_edges: np.ndarray           # (c, 2) the edges cut, one new node each
    fractions: np.ndarray           # (c,) where, from the first node
    cut_faces: list                 # face keys between the two sides
    zeros: np.ndarray               # nodes snapped onto the cut
    state: np.ndarray               # per node ±1, 0 on the cut, 2 away from it


class Cutter:
    """Cuts one body. `model`: its BodyModel; `solver` (optional): its ImplicitEuler, whose
    positions locate the blade and whose state the new nodes join; `compliance` (optional): a
    CuttingCompliance kept up to date; `snap`: the snapping fraction (0: the naive split, without
    snapping or the quality bound, kept for comparison)."""

    def __init__(self, model, solver=None, compliance=None, snap: float = SNAP):
        self.model, self.solver, self.compliance = model, solver, compliance
        self.snap = float(snap)
        self.surface = CutSurface()
        self.pending: set = set()               # cut faces whose two sides still share them
        self.cut_nodes: set = set()             # nodes on the cut
        self.cut_keys: set = set()              # boundary faces on the cut (sorted node ids)
        edges = model.points[model.tets[:, [1, 2, 3, 2, 3, 3]]] - model.points[model.tets[:, [0, 0, 0, 1, 1, 2]]]
        self.spacing = float(np.median(np.linalg.norm(edges, axis=2)))
        self.reports: list[CutReport] = []

    def positions(self) -> np.ndarray:
        return self.solver.positions() if self.solver is not None else self.model.points

    # ---- the step -----------------------------------------------------------------------------

    def cut(self, triangles) -> CutReport:
        """Sweep these triangles (k, 3, 3; tissue.cutting.surface) and cut what the surface so far
        has crossed whole."""
        report = CutReport()
        start = time.perf_counter()
        self.surface.add(triangles)
        x = self.positions()
        plan = self._plan(np.asarray(triangles).reshape(-1, 3, 3), x, self.snap)
        backend.sync()       # (the clocks read after the device's work: a GPU runs behind)
        report.seconds["geometry"] = time.perf_counter() - start
        start = time.perf_counter()
        model = self.model
        # velocities are read only when nodes are to be added (a read costs milliseconds)
        v = self.solver.velocities() if self.solver is not None and len(plan.elements) else None
        report.split, report.created, report.snapped = len(plan.elements), len(plan.sub_tets), len(plan.zeros)
        report.min_dihedral, report.max_condition = quality(self._rest_with(plan), plan.sub_tets)
        u, w = plan.cut_edges.T if len(plan.cut_edges) else (np.zeros(0, np.int64),) * 2
        t = plan.fractions[:, None]
        new_x = [(1 - t) * x[u] + t * x[w]]
        new_v = [(1 - t) * v[u] + t * v[w]] if v is not None else [np.zeros((0, 3))]
        if len(plan.elements):
            model.remove_elements(plan.elements)
            ids = model.add_nodes((1 - t) * model.points[u] + t * model.points[w])
            model.add_elements(plan.sub_tets)
            self.cut_nodes.update(ids.tolist())
        self.cut_nodes.update(plan.zeros.tolist())
        state = np.concatenate([plan.state, np.zeros(len(plan.cut_edges), np.int64)])
        x_all = np.concatenate([x] + new_x)
        self.pending.update(plan.cut_faces)
        self.pending.update(self._faces_on_cut(state, x_all))
        elements, tets, sources = duplications(model, self.pending)
        if len(sources):
            held = model.held[sources] == HELD
            model.remove_elements(elements)
            copies = model.add_nodes(model.points[sources])
            tets[tets < 0] = copies[-1 - tets[tets < 0]]
            model.add_elements(tets)
            if held.any():
                model.set_held(np.concatenate([model.held_nodes, copies[held]]))
            self.cut_nodes.update(copies.tolist())
            new_x.append(x_all[sources])
            if self.solver is not None:
                v = self.solver.velocities()[:len(x)] if v is None else v     # (no split: none added yet)
                new_v.append(np.concatenate([v] + new_v)[sources])
        self.pending = still_interior(model, self.pending)
        report.nodes_added, report.separated = sum(len(a) for a in new_x), len(sources)
        if report.nodes_added:
            self._mark_cut_faces(np.concatenate([x] + new_x))
        backend.sync()
        report.seconds["model"] = time.perf_counter() - start
        start = time.perf_counter()
        if self.solver is not None and report.nodes_added:   # only the new nodes' rows
            self.solver.set_nodes(np.arange(len(x), model.n_nodes), np.concatenate(new_x), np.concatenate(new_v))
        backend.sync()
        report.seconds["state"] = time.perf_counter() - start
        start = time.perf_counter()
        if self.compliance is not None:
            self.compliance.update()
        backend.sync()
        report.seconds["compliance"] = time.perf_counter() - start
        self.reports.append(report)
        return report

    def cut_faces(self) -> np.ndarray:
        """A mask of `model.boundary_faces()`: the faces that a cut opened."""
        keys = np.sort(self.model.boundary_faces(), axis=1)
        return np.array([tuple(k) in self.cut_keys for k in keys.tolist()], dtype=bool).reshape(-1)

    def _mark_cut_faces(self, x: np.ndarray) -> None:
        """Record the boundary faces this step opened: all three nodes on the cut, and lying on
        the swept surface (within the snapping distance, facing along its normal), where they are
        now (the pieces move apart later)."""
        faces = self.model.boundary_faces()
        on = np.zeros(self.model.n_nodes, bool)
        on[list(self.cut_nodes)] = True
        keys = np.sort(faces, axis=1)
        new = on[faces].all(axis=1)
        new[new] = [tuple(k) not in self.cut_keys for k in keys[new].tolist()]
        if not new.any():
            return
        p = x[faces[new]]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        reach = max(self.snap, 0.05) * self.spacing
        centres = p.mean(axis=1)        # (a triangle within reach has its box within reach of theirs)
        distance, _, nearest = self.surface.distances(centres, self.surface.near(centres.min(axis=0) - reach,
                                                                                 centres.max(axis=0) + reach))
        aligned = np.abs(np.einsum("ki,ki->k", normal, self.surface.normals[nearest])) >= 0.5
        close = distance <= reach
        self.cut_keys.update(map(tuple, keys[new][aligned & close].tolist()))

    # ---- planning -----------------------------------------------------------------------------

    def _rest_with(self, plan: _Plan) -> np.ndarray:
        rest = self.model.points
        if not len(plan.cut_edges):
            return rest
        t = plan.fractions[:, None]
        u, w = plan.cut_edges.T
        return np.concatenate([rest, (1 - t) * rest[u] + t * rest[w]])

    def _plan(self, patch: np.ndarray, x: np.ndarray, snap: float) -> _Plan:
        """Which elements to split and how, with the quality bound enforced when snap > 0."""
        model, surface = self.model, self.surface
        tets = model.tets.astype(np.int64)
        h = self.spacing
        lo, hi = patch.reshape(-1, 3).min(axis=0) - h, patch.reshape(-1, 3).max(axis=0) + h
        candidates = _boxes_meeting(x, tets, lo, hi)
        near = surface.near(lo - h, hi + h)
        nodes = np.unique(tets[candidates])
        distance, side, _ = surface.distances(x[nodes], near)
        edges = _unique_rows(np.sort(tets[candidates][:, _EDGES].reshape(-1, 2), axis=1), model.n_nodes)
        length = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
        shortest = np.full(model.n_nodes, np.inf)
        np.minimum.at(shortest, edges.reshape(-1), np.repeat(length, 2))
        state = np.full(model.n_nodes, 2, dtype=np.int64)        # 2: not near the cut
        state[nodes] = side.astype(np.int64)
        zero = distance <= max(snap, 1e-9) * shortest[nodes]
        state[nodes[zero]] = 0
        state[nodes[np.isin(nodes, list(self.cut_nodes))]] = 0   # once on the cut, always: it runs through it
        rest = model.points
        for _ in range(64):
            element_states = state[tets[candidates]]
            cross = element_states[:, _EDGES[:, 0]] * element_states[:, _EDGES[:, 1]] == -1
            pairs = np.sort(tets[candidates][:, _EDGES][cross], axis=1)
            pairs = _unique_rows(pairs, model.n_nodes)
            t, _ = surface.crossings(x[pairs[:, 0]], x[pairs[:, 1]], near)
            ends = np.zeros(0, np.int64)
            if snap > 0:                     # cut points within snap of an end snap to it
                ends = np.r_[pairs[t < snap, 0], pairs[t > 1 - snap, 1]]
            if len(ends):
                state[ends] = 0
                continue
            crossed = {tuple(p): f for p, f in zip(pairs.tolist(), t) if np.isfinite(f)}
            # split: a + and a − node, and every +/− edge crossing the surface
            edge_keys = np.sort(tets[candidates][:, _EDGES], axis=2) @ np.array([model.n_nodes, 1])
            hit = np.isin(edge_keys, pairs[np.isfinite(t)] @ np.array([model.n_nodes, 1]))
            split = np.flatnonzero((element_states == 1).any(axis=1) & (element_states == -1).any(axis=1)
                                   & (hit | ~cross).all(axis=1))
            cut_edges = _unique_rows(np.sort(tets[candidates[split]][:, _EDGES][cross[split]].reshape(-1, 2), axis=1),
                                     model.n_nodes)
            in_split = set(candidates[split].tolist())
            hanging = [p for p in cut_edges.tolist() if any(e not in in_split for e in sharing(model, p))]
            if hanging:                      # an element around a cut edge is not split: snap it
                for p in hanging:
                    state[p[0] if crossed[tuple(p)] < 0.5 else p[1]] = 0
                continue
            fractions = np.array([crossed[tuple(p)] for p in cut_edges.tolist()])
            ids = {tuple(p): model.n_nodes + i for i, p in enumerate(cut_edges.tolist())}
            points = np.concatenate([rest, (1 - fractions[:, None]) * rest[cut_edges[:, 0]]
                                     + fractions[:, None] * rest[cut_edges[:, 1]]]) if len(cut_edges) else rest
            pieces, faces, parents = [], [], []
            for k in split.tolist():
                e = candidates[k]
                sub, _, cut = split_element(tets[e], element_states[k], ids, points)
                pieces.append(sub)
                parents += [k] * len(sub)
                faces += [face_key(f) for f in cut]
            sub_tets = np.concatenate(pieces) if pieces else np.zeros((0, 4), np.int64)
            if snap > 0 and len(sub_tets):   # the quality bound: snap the cut of a violating element
                bad = np.unique(np.array(parents)[~within_bound(points, sub_tets)])
                if len(bad):
                    for k in bad.tolist():
                        e = candidates[k]
                        for (i, j), c in zip(_EDGES, cross[k]):
                            if c:
                                p = tuple(sorted((tets[e, i], tets[e, j])))
                                state[p[0] if crossed[p] < 0.5 else p[1]] = 0
                    continue
            zeros = nodes[state[nodes] == 0]
            return _Plan(candidates[split], sub_tets, cut_edges, fractions, faces, zeros, state)
        raise TissueError("cut: the split did not settle in 64 rounds of snapping")

    def _faces_on_cut(self, state: np.ndarray, x: np.ndarray) -> list:
        """After the split: interior faces whose three nodes are on the cut, between elements on
        its two sides, inside the swept surface (the cut runs along them). An element's side is
        that of its nodes off the cut, or, all four on it, of its centre."""
        model = self.model
        on = np.flatnonzero(state == 0)
        if len(on) == 0:
            return []
        elements = np.unique(incident_elements(model, on))
        tets = model.tets[elements].astype(np.int64)
        s = state[tets]
        off = np.where(np.abs(s) == 1, s, 0)
        side = np.sign(off.sum(axis=1))
        side[(off == 1).any(axis=1) & (off == -1).any(axis=1)] = 0          # mixed: no side
        faces = tets[:, _TRIPLES].reshape(-1, 3)                              # 4 per element
        centred = (s == 0).all(axis=1)
        if centred.any():   # all four on the cut: with most of its neighbours, else by its centre
            _, inverse = _unique_rows(np.sort(faces, axis=1), model.n_nodes, return_inverse=True)
            inverse = inverse.reshape(-1)
            decided = np.zeros(inverse.max() + 1)
            np.add.at(decided, inverse, np.repeat(np.where(centred, 0, side), 4))
            vote = np.sign(decided[inverse].reshape(-1, 4).sum(axis=1))[centred]
            centre = self.surface.distances_near(x[tets[centred]].mean(axis=1), self.spacing)[1]
            side[centred] = np.where(vote != 0, vote, centre)
        owner_side = np.repeat(side, 4)
        zero = (s[:, _TRIPLES] == 0).all(axis=2).reshape(-1) & (owner_side != 0)
        if not zero.any():
            return []
        keys, inverse, counts = _unique_rows(np.sort(faces[zero], axis=1), model.n_nodes, return_inverse=True,
                                             return_counts=True)
        total = np.zeros(len(keys))
        np.add.at(total, inverse.reshape(-1), owner_side[zero])
        opposite = (counts == 2) & (total == 0)                             # a + and a − element
        keys = keys[opposite]
        p = x[keys]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        normal *= (self.spacing / np.linalg.norm(normal, axis=1))[:, None]
        centre = p.mean(axis=1)
        t, _ = self.surface.crossings(centre - normal, centre + normal)
        return list(map(tuple, keys[np.isfinite(t)].tolist()))         # (rows sorted: their face keys)


def _boxes_meeting(x: np.ndarray, tets: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The elements whose bounding box meets the box [lo, hi]: per node 6 bits (x ≤ hi, x ≥ lo per
    axis), or-ed over each element's corners (gathering the corners' coordinates and reducing over
    them costs several times more)."""
    bits = ((x <= hi) * np.array([1, 2, 4]) + (x >= lo) * np.array([8, 16, 32])).sum(axis=1).astype(np.uint8)
    corners = bits[tets]
    return np.flatnonzero((corners[:, 0] | corners[:, 1] | corners[:, 2] | corners[:, 3]) == 63)


def _unique_rows(rows: np.ndarray, base: int, **options):
    """np.unique(rows, axis=0) for rows of ids below `base` (the same rows in the same order, and
    the same return_inverse / return_counts), through one integer key per row: numpy's row-wise
    unique sorts a structured view, several times slower."""
    rows = np.asarray(rows, dtype=np.int64)
    keys = np.zeros(len(rows), dtype=np.int64)
    for column in rows.T:
        keys = keys * base + column
    _, first, *extra = np.unique(keys, return_index=True, **options)
    return (rows[first], *extra) if extra else rows[first]
