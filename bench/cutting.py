"""Cutting benchmark (paper §4.3.1): real cut steps along the `liver_cut` scene's predefined line,
on the liver at about 1,607 and 3,874 tetrahedra (the paper: 22 and 64 ms per compliance update
on a GTX 285, about 2 nodes added or removed per step).

Each step the blade advances STEP_LENGTH along the line and `Cutter.cut` splits and separates what
the swept surface has crossed (tissue.cutting). Per step that changed the mesh:
  - the whole cut step split by stage: geometry (surface queries, split plan with the quality
    bound), model edits (FEM data, mass, gather index, boundary, held nodes, the solver's state
    arrays), the new nodes' state, the compliance update (eager: folded into C every step, the
    paper's cost; lazy: low-rank factors kept, folded past FOLD_RANK), and the contact rows (the
    contact stage re-reading the surface, its samples, held masks and the compliance);
  - the nodes added and elements split (the compliance's rank follows them);
  - the error of both compliances against the direct inverse of the freshly assembled matrix
    (relative to max |C|), after the first and the last cut step;
  - the worst quality (smallest dihedral angle, largest condition number) of the elements created,
    and of a naive split (no snapping, no bound) of the same cut on a copy of the mesh.
Medians over the cut steps; kernels are compiled by a warm-up cut on a small box first.

Then the lazy update's cost against its fold threshold FOLD_RANK (0 to 480, at the larger mesh).

Then the eager fold beside this machine's memory floor: C ← C − T Uᵀ (tissue.cutting.compliance's
fold: the upper triangle in place by dgemm, mirrored) at the ranks an eager step adds, on a C of
the larger mesh's size, against a plain copy of its n² float64 (read n², write n²: what any pass
over C costs at least).

With `--versus COMMIT`: the cut steps at the larger mesh in this checkout and in COMMIT, in
subprocesses that alternate round after round (bench.common.alternate_with_commit): per round the
medians by stage, then the median over rounds.

Also (issue #12's target): a topology edit of 10 elements on a live ~4,000-tetrahedron body,
within its reserved capacity: remove 10 elements, add 2 nodes (centroids of two of them) and 16
elements (8 back, the 2 split into 4 around the new nodes), with the solver's state and assembled
blocks following; median ms over repetitions, state allocations and kernels compiled (none).

    python -m bench.cutting [--versus COMMIT] [--rounds 3]
"""

import argparse
import os
import time
from pathlib import Path

# One BLAS thread unless told otherwise (set before numpy loads OpenBLAS): the compliance's
# products are small, and on this shared 2-core machine a second OpenBLAS thread spins against
# the other processes: at load average ~8, lazy's median went from 17.6 ms (one thread) to
# 104 ms (two), eager's from 93 to 404 (commit 8fb48c5, same session).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.linalg

from bench.common import alternate_with_commit, machine, print_machine, run_child, write_results  # noqa: E402
from scenes.liver_cut import LiverCut  # noqa: E402
from tissue import backend  # noqa: E402
from tissue.body import held_nodes  # noqa: E402

FOLD_RANK = 240
STEP_LENGTH = 0.002          # m of blade travel per step
SIZES = (1607, 3874)


def build(target: int):
    """The scene's liver (held as in liver_cut), its solver at rest, a contact stage on a tray,
    eager and lazy compliances and the cutter, and a naive cutter on a copy."""
    from tissue.contact.obstacles import Plane, RigidObstacle
    from tissue.contact.pipeline import Contact, ContactStage
    from tissue.cutting import CuttingCompliance
    from tissue.cutting.cutter import Cutter
    from tissue.cutting.surface import CutPath
    from tissue.fem import CorotationalFEM, Material
    from tissue.fem.model import BodyModel
    from tissue.mesh.organs import organ_mesh
    from tissue.solver import CGSettings, ImplicitEuler

    scene = LiverCut()
    spec, cut, s = scene.liver, scene.cut, scene.solver
    mesh = organ_mesh("liver", target_tets=target)
    material = Material(young=spec.young, poisson=spec.poisson, density=spec.density)
    fem = CorotationalFEM(mesh, material, rotation=spec.rotation)
    held = held_nodes(mesh.points, spec.fixed)
    solver = ImplicitEuler(fem, dt=scene.dt, rayleigh_mass=s.rayleigh_mass, rayleigh_stiffness=s.rayleigh_stiffness,
                           cg=CGSettings(max_iterations=s.cg_iterations, preconditioner=s.preconditioner), fixed=held)
    fem.model.reserve(nodes=fem.model.n_nodes // 4, elements=fem.model.n_elements // 4,   # as the scene does
                      slots=fem.model.incidence_rows.shape[1] + 8)
    args = (fem.model, scene.dt, s.rayleigh_mass, s.rayleigh_stiffness)
    updates = {"eager": CuttingCompliance(*args), "lazy": CuttingCompliance(*args, fold_rank=FOLD_RANK)}
    contact = ContactStage([solver], [RigidObstacle(Plane((0.0, 0.0, -0.1)))], Contact(distance=2e-3))
    contact.follow_compliance(0, updates["eager"])
    lo, hi = mesh.bounds()
    path = CutPath(lo + np.asarray(cut.path).reshape(-1, 3) * (hi - lo), cut.direction, cut.depth)
    naive_model = BodyModel(mesh, material)
    return dict(mesh=mesh, model=fem.model, solver=solver, updates=updates, contact=contact, path=path,
                material=material, scene=scene, held=held, cutter=Cutter(fem.model, solver),
                naive=Cutter(naive_model, snap=0.0))


def direct_error(b, C: np.ndarray) -> float:
    from tissue.solver.reference import rest_matrix

    s = b["scene"].solver
    model = b["model"]
    A = rest_matrix(model.mesh(), b["material"], b["scene"].dt, s.rayleigh_mass, s.rayleigh_stiffness)
    free = np.flatnonzero(np.repeat(model.held == 0, 3))
    reference = np.zeros(A.shape)
    reference[np.ix_(free, free)] = scipy.linalg.inv(A[free][:, free].toarray())
    return float(np.abs(C - reference).max() / np.abs(reference).max())


def warm_up() -> None:
    """Compile every kernel a cut step launches (once per process, whatever the mesh)."""
    from tissue.cutting import CuttingCompliance
    from tissue.cutting.cutter import Cutter
    from tissue.cutting.surface import CutPath
    from tissue.fem import CorotationalFEM, Material
    from tissue.mesh import box
    from tissue.solver import ImplicitEuler

    fem = CorotationalFEM(box(size=(0.1, 0.04, 0.04), cells=(4, 2, 2)), Material())
    solver = ImplicitEuler(fem, dt=0.02, fixed=[0])
    compliances = [CuttingCompliance(fem.model, 0.02), CuttingCompliance(fem.model, 0.02, fold_rank=FOLD_RANK)]
    cutter = Cutter(fem.model, solver)
    path = CutPath([[0.047, -0.01, 0.05], [0.049, 0.05, 0.05]], [0, 0, -1], 0.1)
    for i in range(4):
        cutter.cut(path.sweep(path.length * i / 4, path.length * (i + 1) / 4))
        for c in compliances:
            c.update()
            c.rows(np.arange(6))


def edit_timing(repeats: int = 60) -> dict:
    """Median ms of a 10-element edit (see the module docstring) on a live 3,960-tet box."""
    from tissue import compilation
    from tissue.fem import CorotationalFEM, Material
    from tissue.mesh import box
    from tissue.solver import ImplicitEuler

    mesh = box(size=(0.11, 0.1, 0.06), cells=(11, 10, 6))
    solver = ImplicitEuler(CorotationalFEM(mesh, Material(3e3, 0.3, 1000.0)), 0.02, gravity=(0.0, 0.0, 0.0))
    model, rng = solver.model, np.random.default_rng(0)
    model.reserve(nodes=2 * repeats + 8, elements=6 * repeats + 64, slots=2 * model.incidence_rows.shape[1])
    solver.step()
    seconds = {"remove": [], "add_nodes": [], "add_elements": [], "edit": [], "edit_cpu": []}
    for i in range(repeats + 3):
        if i == 3:       # after the warm-up edits (first use compiles; the blocks' pattern grows once)
            start, allocations = compilation.count(), solver.allocations
            growths = model.growths
        ids = rng.choice(model.n_elements, 10, replace=False)
        tets = model.tets[ids].astype(np.int64)
        backend.sync()
        c0 = time.process_time()
        t0 = time.perf_counter()
        model.remove_elements(ids)
        t1 = time.perf_counter()
        centres = model.add_nodes(model.points[tets[:2]].mean(axis=1))
        t2 = time.perf_counter()
        model.add_elements(np.concatenate([tets[2:], _split_into_four(tets[:2], centres)]))
        backend.sync()
        t3 = time.perf_counter()
        c3 = time.process_time()
        for k, elapsed in zip(seconds, (t1 - t0, t2 - t1, t3 - t2, t3 - t0, c3 - c0)):
            seconds[k].append(1e3 * elapsed)
        solver.step()
    return dict(tets=mesh.n_tets, elements_removed=10, nodes_added=2, elements_added=16, repeats=repeats,
                median_ms={k: float(np.median(v[3:])) for k, v in seconds.items()},
                state_allocations=solver.allocations - allocations, model_growths=model.growths - growths,
                kernels_compiled=compilation.count() - start)


def _split_into_four(tets: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Each tet (a, b, c, d) as the 4 tets joining one of its faces to its centre."""
    faces = np.array([[1, 3, 2], [0, 2, 3], [0, 3, 1], [0, 1, 2]])
    return np.array([[t[f[0]], t[f[1]], t[f[2]], c] for t, c in zip(tets, centres) for f in faces])


def run(target: int) -> dict:
    b = build(target)
    model, updates, contact, cutter = b["model"], b["updates"], b["contact"], b["cutter"]
    steps = int(np.ceil(b["path"].length / STEP_LENGTH))
    rows = []
    errors = {mode: [] for mode in updates}
    naive = {"min_dihedral": np.inf, "max_condition": 1.0}
    for i in range(steps):
        patch = b["path"].sweep(i * STEP_LENGTH, (i + 1) * STEP_LENGTH)
        backend.sync()
        cpu = time.process_time()
        report = cutter.cut(patch)
        backend.sync()
        row = {k: 1e3 * v for k, v in report.seconds.items()}
        row["cut_cpu"] = 1e3 * (time.process_time() - cpu)
        for mode, update in updates.items():
            cpu, start = time.process_time(), time.perf_counter()
            update.update()
            backend.sync()
            row[f"compliance_{mode}"] = 1e3 * (time.perf_counter() - start)
            row[f"compliance_{mode}_cpu"] = 1e3 * (time.process_time() - cpu)
        cpu, start = time.process_time(), time.perf_counter()
        if contact._edited:
            contact._follow_edits()
        backend.sync()
        row["contact_rows"] = 1e3 * (time.perf_counter() - start)
        row["contact_rows_cpu"] = 1e3 * (time.process_time() - cpu)
        naive_report = b["naive"].cut(patch)
        naive["min_dihedral"] = min(naive["min_dihedral"], naive_report.min_dihedral)
        naive["max_condition"] = max(naive["max_condition"], naive_report.max_condition)
        if report.nodes_added == 0 and report.split == 0:
            continue
        row.update(step=i, nodes_added=report.nodes_added, split=report.split, created=report.created,
                   min_dihedral=report.min_dihedral, max_condition=report.max_condition,
                   lazy_rank=updates["lazy"].rank)
        rows.append(row)
        if len(rows) == 1:
            for mode, update in updates.items():
                errors[mode].append(direct_error(b, update.dense()))
    for mode, update in updates.items():
        errors[mode].append(direct_error(b, update.dense()))
    stages = ("geometry", "model", "state", "contact_rows")
    medians = {k: float(np.median([r[k] for r in rows])) for k in stages + ("compliance_eager", "compliance_lazy")}
    whole = {mode: float(np.median([sum(r[k] for k in stages) + r[f"compliance_{mode}"] for r in rows]))
             for mode in updates}
    # CPU time of this process (all its threads): what the other processes' load on the shared
    # cores does not inflate, unlike the wall time (a busy BLAS thread still counts).
    cpu = {f"compliance_{mode}": float(np.median([r[f"compliance_{mode}_cpu"] for r in rows])) for mode in updates}
    cpu.update({f"whole_step_{mode}": float(np.median([r["cut_cpu"] + r["contact_rows_cpu"] + r[f"compliance_{mode}_cpu"]
                                                       for r in rows])) for mode in updates})
    means = {f"compliance_{mode}": float(np.mean([r[f"compliance_{mode}"] for r in rows])) for mode in updates}
    means.update({f"compliance_{mode}_cpu": float(np.mean([r[f"compliance_{mode}_cpu"] for r in rows]))
                  for mode in updates})
    created = [r for r in rows if r["created"]]
    pieces = len(np.unique(_pieces(model)))
    return {"tets": b["mesh"].n_tets, "nodes": b["mesh"].n_points, "held": len(b["held"]), "steps": steps,
            "cut_steps": len(rows), "step_length_m": STEP_LENGTH, "fold_rank": FOLD_RANK,
            "tets_after": model.n_elements, "nodes_after": model.n_nodes, "pieces_after": pieces,
            "median_ms": medians, "whole_step_median_ms": whole, "cpu_median_ms": cpu, "mean_ms": means,
            "nodes_added_median": float(np.median([r["nodes_added"] for r in rows])),
            "nodes_added_max": int(max(r["nodes_added"] for r in rows)),
            "error_first_last": errors, "lazy_folds": updates["lazy"].folds,
            "worst_created": {"min_dihedral": min(r["min_dihedral"] for r in created),
                              "max_condition": max(r["max_condition"] for r in created)},
            "worst_naive": naive, "per_step": rows}


def fold_rank_sweep(target: int = SIZES[-1], ranks=(0, 60, 120, 240, 480)) -> dict:
    """The lazy update's cost against its fold threshold: the same cut steps, one compliance per
    threshold (0: eager), each updated after every step; median and mean ms (wall and CPU) over
    the steps that changed the mesh, and the folds."""
    from tissue.cutting import CuttingCompliance

    b = build(target)
    model, s = b["model"], b["scene"].solver
    del b["updates"]                               # (their memory: C is (3 nodes)² floats each)
    updates = {r: CuttingCompliance(model, b["scene"].dt, s.rayleigh_mass, s.rayleigh_stiffness, fold_rank=r)
               for r in ranks}
    wall, cpu = {r: [] for r in ranks}, {r: [] for r in ranks}
    for i in range(int(np.ceil(b["path"].length / STEP_LENGTH))):
        report = b["cutter"].cut(b["path"].sweep(i * STEP_LENGTH, (i + 1) * STEP_LENGTH))
        if report.nodes_added == 0 and report.split == 0:
            continue
        for r, update in updates.items():
            c, t = time.process_time(), time.perf_counter()
            update.update()
            backend.sync()
            wall[r].append(1e3 * (time.perf_counter() - t))
            cpu[r].append(1e3 * (time.process_time() - c))
    return {"tets": b["mesh"].n_tets, "rows": [
        dict(fold_rank=r, folds=updates[r].folds, wall_median_ms=float(np.median(wall[r])),
             wall_mean_ms=float(np.mean(wall[r])), cpu_median_ms=float(np.median(cpu[r])),
             cpu_mean_ms=float(np.mean(cpu[r])), cpu_max_ms=float(np.max(cpu[r]))) for r in ranks]}


def fold_floor(n: int, capacity: int, ranks=(12, 24, 48), repeats: int = 7) -> dict:
    """Median ms (CPU time and wall) of the fold C ← C − T Uᵀ at these ranks on a random symmetric
    C of n dofs within `capacity` (as the compliance keeps it), and of a plain copy of its n²
    float64 into another array: the memory floor of one pass over C (GB/s: 16 n² bytes moved)."""
    from tissue.cutting.compliance import RANK_ROOM, _host_fold

    rng = np.random.default_rng(0)
    C = rng.standard_normal((capacity, capacity))
    C += C.T
    T, U = np.zeros((capacity, FOLD_RANK + RANK_ROOM)), np.zeros((capacity, FOLD_RANK + RANK_ROOM))
    free, copy = np.ones(capacity, bool), np.empty((n, n))

    def clocks(run):
        wall, cpu = [], []
        for _ in range(repeats + 1):
            c, t = time.process_time(), time.perf_counter()
            run()
            wall.append(1e3 * (time.perf_counter() - t))
            cpu.append(1e3 * (time.process_time() - c))
        return {"wall_median_ms": float(np.median(wall[1:])), "cpu_median_ms": float(np.median(cpu[1:]))}

    out = {"n": n, "capacity": capacity, "copy": clocks(lambda: np.copyto(copy, C[:n, :n])), "fold": []}
    out["copy"]["gb_per_s_cpu"] = 16e-6 * n * n / out["copy"]["cpu_median_ms"]
    for rank in ranks:
        U[:n, :rank] = 1e-3 * rng.standard_normal((n, rank))
        X = rng.standard_normal((rank, rank))
        T[:n, :rank] = U[:n, :rank] @ (X + X.T)
        out["fold"].append({"rank": rank, **clocks(lambda: _host_fold(C, T, U, rank, free, n))})
    return out


CHILD = r"""
import json, os, sys
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from bench import cutting
from tissue import backend
backend.init(precision="f64")
cutting.warm_up()
r = cutting.run(int(sys.argv[1]))
print("RESULT " + json.dumps({k: r[k] for k in ("tets", "cut_steps", "median_ms", "whole_step_median_ms", "cpu_median_ms",
                                                "mean_ms")}))
"""


def measure(checkout: Path, target: int) -> dict:
    return run_child(checkout, CHILD, (target,))


def versus(other: str, rounds: int, target: int = SIZES[-1]) -> dict:
    """The cut steps at `target` tetrahedra here and at commit `other`, alternately (see the
    module docstring); per round the medians, then the median over rounds of each."""
    def describe(r):
        w, c = r["whole_step_median_ms"], r["cpu_median_ms"]
        return (f"whole step lazy {w['lazy']:.2f} ms (CPU {c['whole_step_lazy']:.2f}), eager {w['eager']:.2f} "
                f"(CPU {c['whole_step_eager']:.2f}); compliance lazy {r['median_ms']['compliance_lazy']:.2f}, "
                f"eager {r['median_ms']['compliance_eager']:.2f}")

    other, runs = alternate_with_commit(other, rounds, lambda checkout: measure(checkout, target), describe,
                                        prefix="tissue-cutting-")
    summary = {}
    for name, results in runs.items():
        summary[name] = {group: {k: float(np.median([r[group][k] for r in results])) for k in results[0][group]}
                         for group in ("median_ms", "whole_step_median_ms", "cpu_median_ms", "mean_ms")}
    return {"other": other, "target": target, "rounds": runs, "median_over_rounds": summary}


def _pieces(model) -> np.ndarray:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    tets = model.tets
    incidence = sp.csr_matrix((np.ones(tets.size), (np.repeat(np.arange(len(tets)), 4), tets.reshape(-1))),
                              shape=(len(tets), model.n_nodes))
    return connected_components(incidence @ incidence.T)[1]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--versus", help="also measure the cut steps against this commit, alternately")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default="cutting", help="the results' name under bench/results (default cutting)")
    args = parser.parse_args(argv)
    backend.init(precision="f64")
    info = machine()
    print_machine(info)
    print(f"# BLAS threads {os.environ['OPENBLAS_NUM_THREADS']}; load average at start {os.getloadavg()[0]:.1f}")
    compared = None
    if args.versus:
        compared = versus(args.versus, args.rounds)
        for name, m in compared["median_over_rounds"].items():
            print(f"{name:>5} (median of {args.rounds} rounds): whole step lazy {m['whole_step_median_ms']['lazy']:.2f} ms "
                  f"(CPU {m['cpu_median_ms']['whole_step_lazy']:.2f}), eager {m['whole_step_median_ms']['eager']:.2f} "
                  f"(CPU {m['cpu_median_ms']['whole_step_eager']:.2f}); compliance lazy "
                  f"{m['median_ms']['compliance_lazy']:.2f} (CPU {m['cpu_median_ms']['compliance_lazy']:.2f}), eager "
                  f"{m['median_ms']['compliance_eager']:.2f} (CPU {m['cpu_median_ms']['compliance_eager']:.2f})")
    warm_up()
    edit = edit_timing()
    m = edit["median_ms"]
    print(f"topology edit on {edit['tets']} tets (remove 10 elements, add 2 nodes and 16 elements), median ms: "
          f"{m['edit']:.3f} (remove {m['remove']:.3f}, add nodes {m['add_nodes']:.3f}, add elements "
          f"{m['add_elements']:.3f}; CPU time {m['edit_cpu']:.3f}); state allocations {edit['state_allocations']}, growths "
          f"{edit['model_growths']}, kernels compiled {edit['kernels_compiled']}")
    results = []
    for target in SIZES:
        r = run(target)
        results.append(r)
        m, w = r["median_ms"], r["whole_step_median_ms"]
        print(f"\n{r['tets']} tets, {r['nodes']} nodes: {r['cut_steps']} of {r['steps']} steps changed the mesh "
              f"(nodes added per step: median {r['nodes_added_median']:.0f}, max {r['nodes_added_max']}); "
              f"after: {r['tets_after']} tets, {r['nodes_after']} nodes, {r['pieces_after']} pieces")
        print(f"  median ms: geometry {m['geometry']:.2f}, model edits {m['model']:.2f}, state {m['state']:.2f}, "
              f"contact rows {m['contact_rows']:.2f}, compliance eager {m['compliance_eager']:.2f} / lazy "
              f"{m['compliance_lazy']:.2f}")
        print(f"  whole cut step (median ms): eager {w['eager']:.2f}, lazy {w['lazy']:.2f}")
        c, mean = r["cpu_median_ms"], r["mean_ms"]
        print(f"  CPU time (median ms): compliance eager {c['compliance_eager']:.2f} / lazy {c['compliance_lazy']:.2f}; "
              f"whole step eager {c['whole_step_eager']:.2f} / lazy {c['whole_step_lazy']:.2f}")
        print(f"  compliance mean ms (folds included): eager {mean['compliance_eager']:.2f} / lazy "
              f"{mean['compliance_lazy']:.2f}; CPU {mean['compliance_eager_cpu']:.2f} / {mean['compliance_lazy_cpu']:.2f}; "
              f"lazy folds {r['lazy_folds']}")
        print("  error vs direct inverse (first, last cut step): " + "; ".join(
            f"{mode} " + ", ".join(f"{e:.1e}" for e in errs) for mode, errs in r["error_first_last"].items()))
        print(f"  worst created: dihedral {r['worst_created']['min_dihedral']:.1f} deg, condition "
              f"{r['worst_created']['max_condition']:.1f}; naive split: dihedral "
              f"{r['worst_naive']['min_dihedral']:.2f} deg, condition {r['worst_naive']['max_condition']:.1f}")
    last = results[-1]
    floor = fold_floor(3 * last["nodes_after"], 3 * (last["nodes"] + last["nodes"] // 4))
    print(f"\nmemory floor at n = {floor['n']} dofs: a copy of n² float64 {floor['copy']['cpu_median_ms']:.2f} ms CPU "
          f"({floor['copy']['gb_per_s_cpu']:.1f} GB/s), wall {floor['copy']['wall_median_ms']:.2f}; the fold: " + ", ".join(
              f"rank {f['rank']} {f['cpu_median_ms']:.2f} ms CPU (wall {f['wall_median_ms']:.2f})" for f in floor["fold"]))
    sweep = fold_rank_sweep()
    print(f"\nlazy update against its fold threshold ({sweep['tets']} tets; 0: eager), ms:")
    for row in sweep["rows"]:
        print(f"  fold_rank {row['fold_rank']:4d}: CPU median {row['cpu_median_ms']:6.2f}, mean "
              f"{row['cpu_mean_ms']:6.2f}, max {row['cpu_max_ms']:6.1f}; wall median {row['wall_median_ms']:6.2f}, "
              f"mean {row['wall_mean_ms']:6.2f}; {row['folds']} folds")
    write_results(args.out, {"machine": info, "fold_rank_sweep": sweep, "blas_threads": os.environ["OPENBLAS_NUM_THREADS"],
                              "load_average": os.getloadavg(), "step_length_m": STEP_LENGTH, "topology_edit": edit,
                              "results": results, "memory_floor": floor, "versus": compared})


if __name__ == "__main__":
    main()
