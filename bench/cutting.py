"""Cutting benchmark (paper §4.3.1), the compliance update: ms per update of C = A⁻¹ after a cut
step, eager (folded into C every step: the paper's cost) against lazy (low-rank factors kept,
folded when their rank passes FOLD_RANK), on the liver at about 1,607 and 3,874 tetrahedra (the
paper: 22 and 64 ms per update on a GTX 285, about 2 nodes added or removed per step).

A cut step here: two face-adjacent elements removed and each put back as four around a new node at
its centroid (2 nodes and 8 elements added, 2 removed), then one `update()` of each compliance.
The error against the direct inverse of the freshly assembled matrix (relative to max |C|) is
measured after the first and the last step.

    python -m bench.cutting
"""

import time

import numpy as np
import scipy.linalg

from bench.common import machine, print_machine, write_results
from tissue import backend
from tissue.cutting import CuttingCompliance
from tissue.fem.material import Material
from tissue.fem.model import BodyModel
from tissue.mesh.organs import organ_mesh
from tissue.mesh.surface import OUTWARD_FACES
from tissue.solver.reference import rest_matrix

MATERIAL = Material()
DT = 0.01
FOLD_RANK = 240
SIZES = {1607: 14, 3874: 12}     # target tetrahedra: timed steps


def adjacent_pair(model: BodyModel, rng) -> np.ndarray:
    """A random element and one that shares a face with it."""
    tets = model.tets
    while True:
        e = int(rng.integers(len(tets)))
        shared = np.isin(tets, tets[e]).sum(axis=1) == 3
        if shared.any():
            return np.array([e, int(rng.choice(np.flatnonzero(shared)))])


def cut_step(model: BodyModel, rng) -> None:
    elements = adjacent_pair(model, rng)
    tets = model.tets[elements].copy()
    model.remove_elements(elements)
    centres = model.add_nodes(model.points[tets].mean(axis=1))
    faces = tets[:, OUTWARD_FACES[:, ::-1]]                          # apex inside
    model.add_elements(np.concatenate([faces, np.broadcast_to(centres[:, None, None], (2, 4, 1))],
                                      axis=2).reshape(-1, 4))


def direct_error(model: BodyModel, C: np.ndarray) -> float:
    A = rest_matrix(model.mesh(), MATERIAL, DT).toarray()
    reference = scipy.linalg.inv(A)       # no held nodes; every node is in an element
    return float(np.abs(C - reference).max() / np.abs(reference).max())


def run(target: int, steps: int, rng) -> dict:
    mesh = organ_mesh("liver", target_tets=target)
    model = BodyModel(mesh, MATERIAL, node_capacity=mesh.n_points + 2 * steps + 16)
    updates = {"eager": CuttingCompliance(model, DT), "lazy": CuttingCompliance(model, DT, fold_rank=FOLD_RANK)}
    times = {mode: [] for mode in updates}
    ranks, errors = [], {mode: [] for mode in updates}
    for step in range(steps + 1):                  # step 0 compiles: not timed
        cut_step(model, rng)
        for mode, update in updates.items():
            start = time.perf_counter()
            update.update()
            backend.sync()
            if step:
                times[mode].append(1e3 * (time.perf_counter() - start))
        ranks.append(updates["lazy"].rank)
        if step in (1, steps):
            for mode, update in updates.items():
                errors[mode].append(direct_error(model, update.dense()))
    result = {"tets": mesh.n_tets, "nodes": mesh.n_points, "steps": steps, "fold_rank": FOLD_RANK,
              "lazy_folds": updates["lazy"].folds, "lazy_rank_after_each_step": ranks}
    for mode in updates:
        ms = np.array(times[mode])
        result[mode] = {"median_ms": float(np.median(ms)), "mean_ms": float(ms.mean()), "max_ms": float(ms.max()),
                        "error_first_last": errors[mode]}
    return result


def main() -> None:
    backend.init(precision="f64")
    info = machine()
    print_machine(info)
    rng = np.random.default_rng(0)
    results = []
    print(f"{'tets':>6} {'nodes':>6} {'mode':>6} {'median ms':>10} {'mean ms':>8} {'max ms':>8}  error (first, last step)")
    for target, steps in SIZES.items():
        r = run(target, steps, rng)
        results.append(r)
        for mode in ("eager", "lazy"):
            m = r[mode]
            print(f"{r['tets']:>6} {r['nodes']:>6} {mode:>6} {m['median_ms']:>10.1f} {m['mean_ms']:>8.1f} "
                  f"{m['max_ms']:>8.1f}  " + ", ".join(f"{e:.1e}" for e in m["error_first_last"]))
        print(f"#   lazy: {r['lazy_folds']} folds in {steps + 1} steps (fold rank {FOLD_RANK}); rank after each step "
              f"{r['lazy_rank_after_each_step']}")
    write_results("cutting", {"machine": info, "results": results})


if __name__ == "__main__":
    main()
