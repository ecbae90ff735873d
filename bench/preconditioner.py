"""Preconditioners against time (issue #2): the relative error of one implicit-Euler step
against the direct solve, as a function of wall time, for CGSettings.preconditioner = none,
jacobi and multigrid (and a few multigrid settings).

The co-rotational beam of the issue: 21 × 21 × 93 nodes, spacing 0.05, 220,800 tetrahedra, the
z = 0 face fixed, gravity across (-y), E 3000, ν 0.3, density 1, Rayleigh 0.1/0.1, dt 0.02,
"large" rotations, parallel execution. The step measured is the 7th from rest (the issue's
numbers), where the beam is moving; the state before it comes from 6 steps of a tightly converged
solve. Error: ‖dv - dv*‖ / ‖dv*‖ with dv* from scipy's sparse LU of the independently assembled
system (tissue.solver.reference).

Each curve point is CG after k iterations (one iteration per launch, the clock stopped while the
iterate is read), from the start of the step: rotations, assembly and the per-step preconditioner
set-up are included. Then each preconditioner runs real steps capped at the iterations that reach
1e-3: that median is the "time to 1e-3". Medians of 3 repeats, warm-up (compilation) excluded.

    python -m bench.preconditioner           # the issue's beam (~15 min on 2 cores)
    python -m bench.preconditioner --quick   # an 11 × 11 × 47-node beam (~3 min)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import FIGURES, machine, print_machine, write_results

TARGET = 1e-3
STEPS_BEFORE = 6
SETTINGS = dict(dt=0.02, gravity=(0.0, -9.81, 0.0), rayleigh_mass=0.1, rayleigh_stiffness=0.1)
# (label, preconditioner, CGSettings extras, iteration cap of the curve)
VARIANTS = [("none", "none", {}, 4000), ("jacobi", "jacobi", {}, 1500),
            ("multigrid", "multigrid", {}, 60)]
MULTIGRID_VARIANTS = [("multigrid 250 nodes", {"coarse_nodes": 250}), ("multigrid 1000 nodes", {"coarse_nodes": 1000}),
                      ("multigrid degree 1", {"smoothing_degree": 1}), ("multigrid degree 3", {"smoothing_degree": 3})]


def beam(quick: bool):
    from tissue.mesh import box

    cells = np.array((10, 10, 46) if quick else (20, 20, 92))
    mesh = box(size=0.05 * cells, cells=cells)
    return mesh, np.flatnonzero(mesh.points[:, 2] < 1e-9)


def make_solver(mesh, fixed, preconditioner="none", iterations=25, tolerance=0.0, unroll=5, **extras):
    from tissue.fem import CorotationalFEM, Material
    from tissue.solver import CGSettings, ImplicitEuler

    fem = CorotationalFEM(mesh, Material(young=3000.0, poisson=0.3, density=1.0), rotation="large")
    cg = CGSettings(max_iterations=iterations, tolerance=tolerance, preconditioner=preconditioner, **extras)
    return ImplicitEuler(fem, cg=cg, fixed=fixed, execution="parallel", unroll=unroll, **SETTINGS)


def reference(mesh, fixed, x, v) -> tuple[np.ndarray, float]:
    """dv of the step from (x, v) by sparse LU (SuperLU), and the seconds it took."""
    import scipy.sparse.linalg as spla

    from tissue.fem import Material
    from tissue.solver import reference as ref

    start = time.perf_counter()
    system = ref.linearise(mesh, Material(young=3000.0, poisson=0.3, density=1.0), x, v, rotation="large",
                           **SETTINGS)
    free = ref.free_dofs(mesh.n_points, fixed)
    dv = np.zeros(3 * mesh.n_points)
    dv[free] = spla.splu(system.A[free][:, free].tocsc(), permc_spec="MMD_AT_PLUS_A").solve(system.b[free])
    return dv, time.perf_counter() - start


def curve(solver, x, v, dv_ref, cap: int, repeats: int = 3) -> dict:
    """Wall time from the step's start and error of dv after k = 0, 1, ... CG iterations."""
    import taichi as ti

    from tissue.solver.step_kernels import BEGIN_PARALLEL, ITERATE_PARALLEL

    norm = np.linalg.norm(dv_ref)
    samples, errors = [], []
    for repeat in range(repeats + 1):            # the first run compiles: excluded
        solver.set_state(x, v)
        ti.sync()
        start = time.perf_counter()
        k, o, tol = solver.prepare_step()
        BEGIN_PARALLEL(k, o, tol)
        ti.sync()
        times = [time.perf_counter() - start]
        errors = [1.0]
        for _ in range(cap if repeat else 1):
            start = time.perf_counter()
            ITERATE_PARALLEL(k, o)
            ti.sync()
            times.append(times[-1] + time.perf_counter() - start)
            errors.append(float(np.linalg.norm(solver.arrays["dv"].to_numpy()[:len(x)].reshape(-1) - dv_ref) / norm))
            if errors[-1] < 0.1 * TARGET:
                break
        if repeat:
            samples.append(times)
    length = min(len(s) for s in samples)
    times = np.median([s[:length] for s in samples], axis=0)
    return {"seconds": times.tolist(), "errors": errors[:length], "begin_ms": 1e3 * float(times[0])}


def capped_steps(mesh, fixed, x, v, dv_ref, preconditioner, iterations, extras, repeats=3) -> dict:
    """Real steps (begin, CG, end) capped at `iterations`: median wall time and the error."""
    import taichi as ti

    solver = make_solver(mesh, fixed, preconditioner, iterations, **extras)
    samples = []
    for repeat in range(repeats + 1):
        solver.set_state(x, v)
        ti.sync()
        start = time.perf_counter()
        solver.step()
        ti.sync()
        if repeat:
            samples.append(time.perf_counter() - start)
    error = np.linalg.norm(solver.velocities().reshape(-1) - v.reshape(-1) - dv_ref) / np.linalg.norm(dv_ref)
    return {"iterations": iterations, "median_s": float(np.median(samples)), "error": float(error),
            "stages_ms": solver.stats.ms_per_step(skip=1)}


def measure(label, mesh, fixed, x, v, dv_ref, preconditioner, extras, cap) -> dict:
    start = time.perf_counter()
    solver = make_solver(mesh, fixed, preconditioner, cap, unroll=1, **extras)
    setup = time.perf_counter() - start
    row = {"label": label, "preconditioner": preconditioner, **extras, "setup_s": setup,
           **curve(solver, x, v, dv_ref, cap)}
    if preconditioner == "multigrid":
        row["coarse_nodes_kept"] = solver.multigrid.n_coarse
    del solver
    reached = [k for k, e in enumerate(row["errors"]) if e <= TARGET]
    text = f"{label:>22}: set-up {setup:6.1f} s, step start {row['begin_ms']:7.1f} ms"
    if reached:
        k = reached[0]
        row["iterations_to_target"] = k
        row["curve_seconds_to_target"] = row["seconds"][k]
        row["step"] = capped_steps(mesh, fixed, x, v, dv_ref, preconditioner, k, extras)
        per_iteration = 1e3 * (row["seconds"][k] - row["seconds"][0]) / k
        text += (f", {k:4d} iterations to {TARGET:g} ({per_iteration:.1f} ms each): step "
                 f"{row['step']['median_s']:.3f} s, error {row['step']['error']:.2e}")
    else:
        text += f", not at {TARGET:g} after {len(row['errors']) - 1} iterations (error {row['errors'][-1]:.2e})"
    if "coarse_nodes_kept" in row:
        text += f" [{row['coarse_nodes_kept']} coarse nodes]"
    print(text, flush=True)
    return row


def plot(result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in result["preconditioners"]:
        style = "-" if row["label"] in ("none", "jacobi", "multigrid") else ":"
        ax.semilogy(row["seconds"], row["errors"], style, label=row["label"])
    ax.axhline(TARGET, color="grey", lw=0.8)
    ax.axvline(0.5, color="grey", lw=0.8, ls="--")
    ax.set_xlim(0, 3.0)
    ax.set_ylim(1e-4, 1.5)
    ax.set_xlabel("wall time from the start of the step (s)")
    ax.set_ylabel("relative error of dv against the direct solve")
    m = result["machine"]
    ax.set_title(f"{result['mesh']}, step {STEPS_BEFORE + 1}; {m['arch']} {m['precision']}, {m['cores']} cores",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    FIGURES.mkdir(exist_ok=True)
    fig.savefig(FIGURES / "preconditioner.png", dpi=120)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="an 11 × 11 × 47-node beam, main variants only")
    parser.add_argument("--arch", default=None, help="cpu, cuda or vulkan (default: auto)")
    args = parser.parse_args(argv)

    from tissue import backend

    backend.init(arch=args.arch, precision="f64")
    info = machine()
    print_machine(info)
    mesh, fixed = beam(args.quick)
    label = f"beam {mesh.n_points} nodes, {mesh.n_tets} tets"
    print(f"{label}; state after {STEPS_BEFORE} steps from rest (multigrid PCG to 1e-10)", flush=True)
    solver = make_solver(mesh, fixed, "multigrid", 200, tolerance=1e-10)
    for _ in range(STEPS_BEFORE):
        solver.step()
    x, v = solver.positions(), solver.velocities()
    del solver
    dv_ref, direct_s = reference(mesh, fixed, x, v)
    print(f"reference: scipy sparse LU of the assembled step, {direct_s:.1f} s (assembly + factorisation + "
          f"solve); tip sag {-x[:, 1].min():.4f} m", flush=True)
    result = {"machine": info, "mesh": label, "settings": {**SETTINGS, "young": 3000.0, "poisson": 0.3,
                                                           "density": 1.0, "rotation": "large"},
              "measured_step": STEPS_BEFORE + 1, "target": TARGET,
              "reference": {"method": "scipy.sparse.linalg.splu of the assembled step (tissue.solver.reference)",
                            "seconds": direct_s}}
    variants = VARIANTS + ([] if args.quick else
                           [(name, "multigrid", extras, 60) for name, extras in MULTIGRID_VARIANTS])
    result["preconditioners"] = [measure(name, mesh, fixed, x, v, dv_ref, p, extras, cap)
                                 for name, p, extras, cap in variants]
    write_results("preconditioner-quick" if args.quick else "preconditioner", result)
    if not args.quick:
        plot(result)


if __name__ == "__main__":
    main()
