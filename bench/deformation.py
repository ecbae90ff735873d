"""Deformation benchmark (paper §2.3, Fig. 5): ms per step against mesh size, stages, bandwidth,
and the ablations, all in one run on this machine.

Settings of SOFA's liver demo (../shared/REFERENCE-TIMINGS.md): dt 0.02 s, E 3000 Pa, ν 0.3,
density 1, Rayleigh 0.1/0.1, 25 CG iterations (tolerance 1e-9, so all 25 run on the larger
meshes), "large" rotations. Fixed nodes as SOFA's runs: three nodes of the small liver, the
lowest 1% of the height of the other organ meshes, the z = 0 face of the beam.

    python -m bench.deformation            # full run (~10 min on 2 cores)
    python -m bench.deformation --quick    # small meshes only
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from bench.common import FIGURES, ROOT, machine, print_machine, time_steps, write_results

# SOFA, measured on this machine class (REFERENCE-TIMINGS.md): tets -> ms/step ("large").
SOFA_MS = {596: 0.88, 1493: 2.42, 4406: 7.04, 19409: 45.4, 220800: 417.0}
PAPER_FIG5 = {"nodes": 41000, "cpu_fps": 1.4, "gpu_fps": 46.15}


def meshes(quick: bool):
    """(label, mesh, fixed nodes, gravity, SOFA ms/step of the mesh it stands for) by size."""
    from tissue.mesh import box
    from tissue.mesh.organs import organ_mesh

    out = []
    targets = (596, 1493, 4406) if quick else (596, 1493, 4406, 19409)
    for target in targets:
        m = organ_mesh("liver", target_tets=target)
        z = m.points[:, 2]
        if target == 596:   # three nodes near the top, as SOFA's liver demo holds it
            fixed = np.argsort(-z)[:3]
        else:
            fixed = np.flatnonzero(z <= z.min() + 0.01 * (z.max() - z.min()))
        out.append((f"liver {m.n_tets} tets", m, fixed, (0.0, 0.0, -9.81), SOFA_MS[target]))
    beams = [(20, 20, 92)] if quick else [(20, 20, 92), (40, 40, 84)]
    for cells in beams:
        m = box(size=(0.05 * cells[0], 0.05 * cells[1], 0.05 * cells[2]), cells=cells)
        out.append((f"beam {m.n_points} nodes", m, np.flatnonzero(m.points[:, 2] < 1e-9), (0.0, -9.81, 0.0),
                    SOFA_MS.get(m.n_tets)))
    return out


def make_solver(mesh, fixed, gravity, rotation="large", accumulation="gather", execution="auto",
                operator="assembled", iterations=25, preconditioner="none", tolerance=1e-9, split_stages=False):
    from tissue.fem import CorotationalFEM, Material
    from tissue.solver import CGSettings, ImplicitEuler

    fem = CorotationalFEM(mesh, Material(young=3000.0, poisson=0.3, density=1.0), rotation=rotation,
                          accumulation=accumulation)
    return ImplicitEuler(fem, dt=0.02, gravity=gravity, rayleigh_mass=0.1, rayleigh_stiffness=0.1,
                         cg=CGSettings(max_iterations=iterations, tolerance=tolerance,
                                       preconditioner=preconditioner),
                         fixed=fixed, execution=execution, operator=operator, split_stages=split_stages)


def steps_for(n_tets: int) -> int:
    return int(np.clip(2e6 / n_tets, 5, 200))


def stream_copy() -> dict:
    """STREAM-like copy a[i] = b[i] on 2 × 256 MB, as a Taichi kernel and with numpy."""
    import taichi as ti

    n = 32 * 1024 * 1024
    a = ti.field(ti.f64, n)
    b = ti.field(ti.f64, n)

    @ti.kernel
    def copy():
        for i in a:
            a[i] = b[i]

    t = time_steps(copy, 10, warmup=2)
    x = np.ones(n)
    y = np.empty(n)
    samples = []
    for _ in range(5):
        start = time.perf_counter()
        np.copyto(y, x)
        samples.append(time.perf_counter() - start)
    bytes_moved = 2 * 8 * n
    return {"taichi_copy_GBps": bytes_moved / (t["median_ms"] * 1e-3) / 1e9,
            "numpy_copy_GBps": bytes_moved / float(np.median(samples)) / 1e9}


def cg_bytes_per_iteration(solver) -> int:
    """Bytes a CG iteration must move at least (assembled operator): the blocks, their column
    indices and row offsets, and the nodal vectors read and written (p, q, dv, r, z, mass, fixed)."""
    n = solver.fem.n_nodes
    real = 8 if backend.current().precision == "f64" else 4
    return solver.matrix.nbytes + n * (3 * real * 9 + real + 4)


def size_sweep(quick: bool) -> list[dict]:
    rows = []
    for label, mesh, fixed, gravity, sofa_ms in meshes(quick):
        variants = [("serial", "assembled"), ("parallel", "assembled"), ("serial", "matrix_free"),
                    ("parallel", "matrix_free")]
        if mesh.n_tets > 100_000:
            variants = [v for v in variants if v[0] == "parallel"]
        for execution, operator in variants:
            solver = make_solver(mesh, fixed, gravity, execution=execution, operator=operator)
            t = time_steps(solver.step, steps_for(mesh.n_tets))
            if execution == "serial":  # one launch per step: time its two parts in a run of their own
                solver = make_solver(mesh, fixed, gravity, execution=execution, operator=operator,
                                     split_stages=True)
                time_steps(solver.step, steps_for(mesh.n_tets))
            stages = solver.stats.ms_per_step(skip=3)
            row = {"mesh": label, "nodes": mesh.n_points, "tets": mesh.n_tets, "execution": execution,
                   "operator": operator, **t, "stages_ms": stages,
                   "cg_iterations": solver.stats.counters["cg_iterations"],
                   "sofa_ms": sofa_ms}
            if operator == "assembled":
                per_iteration = stages["cg"] * 1e-3 / max(row["cg_iterations"], 1)
                row["cg_GBps"] = cg_bytes_per_iteration(solver) / per_iteration / 1e9
            rows.append(row)
            sofa = f"  SOFA {row['sofa_ms']:.2f} ms ({row['sofa_ms'] / t['median_ms']:.1f}×)" if row["sofa_ms"] else ""
            bandwidth = f"  CG {row['cg_GBps']:.1f} GB/s" if "cg_GBps" in row else ""
            print(f"{label:>22} {execution:>8} {operator:>11}: {t['median_ms']:9.3f} ms/step "
                  f"(rotations+forces {stages['rotations+forces']:.3f}, cg {stages['cg']:.3f}){sofa}{bandwidth}",
                  flush=True)
            del solver
    return rows


def accumulation_ablation(mesh) -> list[dict]:
    """Elastic forces and one stiffness product, each accumulation, launched alone."""
    from tissue.fem import CorotationalFEM, Material

    rows = []
    rng = np.random.default_rng(0)
    x = mesh.points + 1e-3 * rng.standard_normal(mesh.points.shape)
    for accumulation in ("gather", "atomic", "colouring"):
        fem = CorotationalFEM(mesh, Material(3000.0, 0.3, 1.0), accumulation=accumulation)
        xf = fem._vector_field(x)
        out = fem._vector_field(np.zeros_like(x), slot=1)
        fem._rotations_kernel(xf)

        def forces():
            fem.scatter_launch("force", xf)
            fem._gather_kernel(out)

        def product():
            fem.scatter_launch("stiffness", xf)
            fem._gather_kernel(out)

        f = time_steps(forces, 30)
        p = time_steps(product, 30)
        rows.append({"accumulation": accumulation, "forces_ms": f["median_ms"], "product_ms": p["median_ms"],
                     "colours": getattr(fem, "n_colours", None)})
        print(f"  accumulation {accumulation:>9}: forces {f['median_ms']:.3f} ms, K·p {p['median_ms']:.3f} ms"
              + (f" ({fem.n_colours} colours)" if accumulation == "colouring" else ""), flush=True)
    return rows


def step_ablation(mesh, fixed, gravity) -> list[dict]:
    rows = []
    for rotation in ("large", "polar", "invertible"):
        for accumulation in ("gather", "atomic"):
            solver = make_solver(mesh, fixed, gravity, rotation=rotation, accumulation=accumulation)
            t = time_steps(solver.step, steps_for(mesh.n_tets))
            rows.append({"rotation": rotation, "accumulation": accumulation, **t})
            print(f"  step {rotation:>10} {accumulation:>7}: {t['median_ms']:.3f} ms", flush=True)
    return rows


def precision_ablation(quick: bool) -> list[dict]:
    """The size sweep's default variant in float32, in a child process (Taichi's precision is
    fixed at initialisation)."""
    env = dict(os.environ, TISSUE_PRECISION="f32")
    cmd = [sys.executable, "-m", "bench.deformation", "--f32-child"] + (["--quick"] if quick else [])
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def f32_child(quick: bool) -> None:
    from tissue import backend

    backend.init(precision="f32")
    rows = []
    for label, mesh, fixed, gravity, _ in meshes(quick):
        solver = make_solver(mesh, fixed, gravity)
        t = time_steps(solver.step, steps_for(mesh.n_tets))
        rows.append({"mesh": label, "tets": mesh.n_tets, "precision": "f32", **t})
    print(json.dumps(rows))


def beam_accuracy() -> list[dict]:
    """Error of one step of the 41,013-node beam against a converged solve, and its time, for
    plain and block-Jacobi CG. The state is the beam after 7 steps. The reference is the same
    step by Jacobi-PCG to a relative residual of 1e-11: scipy's direct solve of these 123k
    unknowns takes about 4 minutes here (SuperLU), and the tests check CG against it on
    smaller meshes."""
    from tissue.mesh import box

    mesh = box(size=(1.0, 1.0, 4.6), cells=(20, 20, 92))
    fixed = np.flatnonzero(mesh.points[:, 2] < 1e-9)
    warm = make_solver(mesh, fixed, (0.0, -9.81, 0.0), iterations=2000, preconditioner="jacobi", tolerance=1e-8)
    warm.run(7)
    x0, v0 = warm.positions(), warm.velocities()
    converged = make_solver(mesh, fixed, (0.0, -9.81, 0.0), iterations=20000, preconditioner="jacobi",
                            tolerance=1e-11)
    converged.set_state(x0, v0)
    converged.step()
    reference = converged.velocities() - v0
    rows = []
    for preconditioner in ("none", "jacobi"):
        for iterations in (25, 50, 100, 200, 400, 800):
            solver = make_solver(mesh, fixed, (0.0, -9.81, 0.0), iterations=iterations,
                                 preconditioner=preconditioner, tolerance=1e-14)

            def one_step():
                solver.set_state(x0, v0)
                solver.step()

            t = time_steps(one_step, 3, warmup=1)
            error = np.linalg.norm(solver.velocities() - v0 - reference) / np.linalg.norm(reference)
            rows.append({"preconditioner": preconditioner, "iterations": iterations, "error": float(error),
                         "step_ms": t["median_ms"]})
            print(f"  beam one step, {preconditioner:>6} {iterations:4d} iterations: relative error {error:.2e}, "
                  f"{t['median_ms']:.0f} ms", flush=True)
    return rows


def plot(result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.8), dpi=130)
    rows = result["sizes"]
    for execution, operator, style in (("serial", "assembled", "o-"), ("parallel", "assembled", "s-"),
                                       ("serial", "matrix_free", "o--"), ("parallel", "matrix_free", "s--")):
        pts = sorted((r["tets"], r["median_ms"]) for r in rows
                     if r["execution"] == execution and r["operator"] == operator)
        if pts:
            ax.plot(*zip(*pts), style, label=f"tissue {operator.replace('_', '-')}, {execution}")
    f32 = sorted((r["tets"], r["median_ms"]) for r in result.get("float32", []))
    if f32:
        ax.plot(*zip(*f32), "^:", label="tissue assembled, float32")
    ax.plot(list(SOFA_MS), list(SOFA_MS.values()), "kx-", label="SOFA (REFERENCE-TIMINGS)")
    ax.plot(list(SOFA_MS), [v / 3 for v in SOFA_MS.values()], "k:", lw=1, label="target: SOFA / 3")
    ax.axhline(1e3 / PAPER_FIG5["cpu_fps"], color="tab:red", lw=0.8, ls="--")
    ax.axhline(1e3 / PAPER_FIG5["gpu_fps"], color="tab:green", lw=0.8, ls="--")
    ax.text(700, 1e3 / PAPER_FIG5["cpu_fps"] * 1.1, "paper, 41k nodes, CPU 2008", fontsize=7, color="tab:red")
    ax.text(700, 1e3 / PAPER_FIG5["gpu_fps"] * 1.1, "paper, 41k nodes, GTX 280", fontsize=7, color="tab:green")
    ax.set(xscale="log", yscale="log", xlabel="tetrahedra", ylabel="ms per step (25 CG iterations)",
           title=f"Implicit co-rotational FEM step · {result['machine']['cpu'][:40]}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    FIGURES.mkdir(exist_ok=True)
    fig.savefig(FIGURES / "deformation.png")
    print(f"# wrote {(FIGURES / 'deformation.png').relative_to(ROOT)}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small meshes only")
    parser.add_argument("--arch", default=None, help="cpu, cuda or vulkan (default: auto)")
    parser.add_argument("--f32-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.f32_child:
        return f32_child(args.quick)

    from tissue import backend

    backend.init(arch=args.arch, precision="f64")
    info = machine()
    print_machine(info)
    result = {"machine": info, "settings": {"dt": 0.02, "young": 3000.0, "poisson": 0.3, "density": 1.0,
                                            "rayleigh": [0.1, 0.1], "cg_iterations": 25, "rotation": "large"}}
    result["bandwidth"] = stream_copy()
    print(f"copy bandwidth: Taichi {result['bandwidth']['taichi_copy_GBps']:.1f} GB/s, "
          f"numpy {result['bandwidth']['numpy_copy_GBps']:.1f} GB/s", flush=True)
    result["sizes"] = size_sweep(args.quick)
    label, mesh, fixed, gravity, _ = meshes(args.quick)[2]
    print(f"ablation on {label}:")
    result["accumulation"] = accumulation_ablation(mesh)
    result["step_variants"] = step_ablation(mesh, fixed, gravity)
    result["float32"] = precision_ablation(args.quick)
    for row in result["float32"]:
        print(f"  float32 {row['mesh']:>22}: {row['median_ms']:.3f} ms/step")
    if not args.quick:
        print("preconditioning, 41,013-node beam:")
        result["beam_accuracy"] = beam_accuracy()
    write_results("deformation-quick" if args.quick else "deformation", result)
    plot(result)


if __name__ == "__main__":
    main()
