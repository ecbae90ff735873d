"""Frictional contact solvers compared on the problems of bench/contact_problems.py: natural-map
residual against time, and the time to a residual of 1e-6, per problem, in one run.

    python -m bench.contact_problems     # first: writes bench/problems/ (~4 min)
    python -m bench.contact_solvers      # ~5 min on 2 cores; bench/results/contact_solvers.json
                                         # and figures/contact_solvers.png

Solvers (tissue.contact.frictional_contact, warm-started as the problem says):
  gauss_seidel       projected Gauss-Seidel, plain sweeps (anderson=0)
  gs_anderson        the same with Anderson acceleration (depth 5): the contact stage's old default
  newton             semi-smooth Newton on the Alart–Curnier function (tissue.contact.newton)
  auto               Gauss-Seidel with Anderson for AUTO_SWEEPS sweeps, then Newton: the stage's default
With --scenes: the must-show runs, each with the stage's method "auto" and the old "gauss_seidel"
(the stage's default cap, 100 iterations, and tolerance 1e-6 m): bench.stability's press plate cell
(100 steps, "polar") and liver_press at the 4 mm alarm distance (~450 rows, 72 steps); per run the
LCP stage's ms per step (median, max), the largest residual, the steps that ended at the cap
above the tolerance, and the steps of any size (below the row threshold too) above it.

Iteration caps: sweeps for Gauss-Seidel, Newton steps (and fallback sweeps) for Newton. Time is
solve()'s own clock (W uploaded beforehand), the best of REPEATS runs for problems under 100 ms,
and beside it the process's CPU time over the same call (run with OPENBLAS_NUM_THREADS=1 and
Taichi's serial loops, the CPU time is the work, whatever else the shared machine runs).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from bench.common import machine, print_machine, write_results
from bench.contact_problems import PROBLEMS, load

TOL = 1e-6
SOLVERS = {"gauss_seidel": dict(method="gauss_seidel", anderson=0), "gs_anderson": dict(method="gauss_seidel"),
           "newton": dict(method="newton"), "auto": dict(method="auto")}
CAPS = {"gauss_seidel": [2 ** k for k in range(11)], "gs_anderson": [2 ** k for k in range(11)],
        "newton": list(range(1, 16)) + [20, 30], "auto": [1, 4, 16, 17, 18, 19, 20, 22, 24, 28, 32, 40, 48, 64, 80]}
MAX_ITERATIONS = {"gauss_seidel": 1024, "gs_anderson": 1024, "newton": 200, "auto": 300}
REPEATS = 3
BUDGET_S = 8.0           # a curve stops at the first cap whose solve takes longer than this


def run_solver(p: dict, name: str) -> dict:
    from tissue.contact.frictional_contact import FrictionalContactSolver, natural_map_residual

    solver = FrictionalContactSolver(p["W"], p["mu"], check=False, **SOLVERS[name])
    solver.solve(p["q"], TOL, 1, r0=p["r0"])                       # compile, warm up

    def timed(tol, cap):
        best = None
        for _ in range(REPEATS):
            cpu = time.process_time()
            r, info = solver.solve(p["q"], tol, cap, r0=p["r0"])
            info.cpu_s = time.process_time() - cpu
            best = info if best is None or info.time_s < best.time_s else best
            if info.time_s > 0.1:
                break
        return r, best

    r, info = timed(TOL, MAX_ITERATIONS[name])
    check = natural_map_residual(p["W"], p["q"], p["mu"], r)         # recomputed independently of the solver
    curve = []
    for cap in CAPS[name]:
        _, c = timed(1e-14, cap)
        curve.append((c.iterations, 1e3 * c.time_s, c.residual))
        if c.time_s > BUDGET_S or c.iterations < cap:                # converged to 1e-14, or too slow
            break
    return {"iterations": info.iterations, "ms": 1e3 * info.time_s, "cpu_ms": 1e3 * info.cpu_s, "residual": info.residual,
            "residual_numpy": check, "converged": bool(info.converged),
            "curve": {"iterations": [c[0] for c in curve], "ms": [c[1] for c in curve], "residual": [c[2] for c in curve]}}


def compile_solver(method: str) -> None:
    """The solver's kernels compiled (W dense and factored) on a two-contact problem, so that no
    step of the scene runs counts Taichi's compilation as solving time."""
    from tissue.contact import FactoredDelassus
    from tissue.contact.frictional_contact import FrictionalContactSolver

    eye = np.tile(np.eye(3), (2, 1, 1))
    factored = FactoredDelassus(ptr=np.array([0, 1, 2]), col=np.array([0, 3]), segment=np.array([0, 0]), blocks=eye,
                                Q=np.eye(6).ravel(), y_offset=np.array([0, 6]), q_offset=np.array([0]), diagonal=eye)
    for W in (np.eye(6), factored):
        FrictionalContactSolver(W, 0.5, method=method, check=False).solve(np.array([-1.0, 0.2, 0, -1.0, 0, 0.1]), TOL, 2)


def scene_runs(methods=("auto", "gauss_seidel")) -> dict:
    """The press plate cell and liver_press at ~450 rows, stepped with each contact method (its
    kernels compiled beforehand)."""
    import dataclasses

    from bench import contact, stability
    from tissue.contact import pipeline

    out = {}
    original = pipeline.Contact.__init__
    for method in methods:
        compile_solver(method)
        # Every Contact built during the run takes this method (the stability cells build their own).
        def init(self, *args, _m=method, **kwargs):
            original(self, *args, **kwargs)
            self.method = _m

        pipeline.Contact.__init__ = init
        try:
            cell = next(c for c in stability.contact_cells(("polar",)) if c["case"] == "press")
            stats, cpu = [], []
            stage_init, stage_solve = pipeline.ContactStage.__init__, pipeline.ContactStage._solve

            def keep(self, *args, **kwargs):
                stage_init(self, *args, **kwargs)
                stats.append(self.stats)
                cpu.append([])

            def solve(self, *args, **kwargs):        # the LCP stage's CPU time, beside its wall time
                start = time.process_time()
                out = stage_solve(self, *args, **kwargs)
                cpu[-1].append(time.process_time() - start)
                return out

            pipeline.ContactStage.__init__, pipeline.ContactStage._solve = keep, solve
            try:
                result = stability.simulate(cell)
                sim = contact.press("warped", [f"contact.distance={contact.WIDE_DISTANCE}", f"contact.method={method}"])
                for _ in range(72):
                    sim.step()
            finally:
                pipeline.ContactStage.__init__, pipeline.ContactStage._solve = stage_init, stage_solve
        finally:
            pipeline.Contact.__init__ = original
        for name, st, cpu_s, min_rows in (("press_plate", stats[0], cpu[0], 1000), ("liver450", stats[-1], cpu[-1], 420)):
            rows = np.array(st.history["rows"])
            keep_steps = rows >= min_rows
            lcp = 1e3 * np.array(st.times["lcp"])[keep_steps]
            lcp_cpu = 1e3 * np.array(cpu_s)[keep_steps[np.array(st.history["rows"]) > 0]] if len(cpu_s) else np.zeros(1)
            res = np.array(st.history["gs_residual"])[keep_steps]
            its = np.array(st.history["gs_iterations"])[keep_steps]
            entry = {"steps": int(keep_steps.sum()), "rows_max": int(rows.max()), "lcp_ms_median": float(np.median(lcp)),
                     "lcp_ms_max": float(lcp.max()), "lcp_over_1s": int(np.sum(lcp > 1e3)),
                     "lcp_cpu_ms_median": float(np.median(lcp_cpu)), "lcp_cpu_ms_max": float(lcp_cpu.max()),
                     "lcp_cpu_over_1s": int(np.sum(lcp_cpu > 1e3)), "lcp_cpu_ms": [round(float(x), 1) for x in lcp_cpu],
                     "residual_max": float(res.max()),
                     "iterations_median": float(np.median(its)),
                     "steps_at_cap_above_tol": int(np.sum((its >= 100) & (res > TOL))),
                     "steps_above_tol_any_rows": int(np.sum(np.array(st.history["gs_residual"]) > TOL))}
            if name == "press_plate":
                entry.update(outcome=result["outcome"], energy_net=result.get("energy_net"),
                             penetration_max_mm=1e3 * result.get("penetration_max", np.nan))
            out.setdefault(name, {})[method] = entry
            print(f"{name:<12} {method:<13} {entry['steps']:>4} steps ≥ {min_rows} rows: lcp {entry['lcp_ms_median']:.1f} ms "
                  f"median, {entry['lcp_ms_max']:.1f} max, {entry['lcp_over_1s']} over 1 s (CPU {entry['lcp_cpu_ms_median']:.1f} "
                  f"median, {entry['lcp_cpu_ms_max']:.1f} max, {entry['lcp_cpu_over_1s']} over 1 s); iterations {entry['iterations_median']:.0f}; residual max "
                  f"{entry['residual_max']:.1e}; {entry['steps_at_cap_above_tol']} at the cap above {TOL:g} "
                  f"({entry['steps_above_tol_any_rows']} steps of any size above it)", flush=True)
    return out


def plot(results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.common import FIGURES

    groups = {"press plate (2,166 rows)": "press", "liver_press, 450 rows": "liver450", "stack": "stack",
              "pile": "pile", "many contacts on one body": "many"}
    fig, axes = plt.subplots(1, len(groups), figsize=(3.2 * len(groups), 3.4), sharey=True)
    colours = dict(zip(SOLVERS, ("tab:grey", "tab:blue", "tab:red", "tab:green")))
    for ax, (title, prefix) in zip(axes, groups.items()):
        names = [k for k in results if k.startswith(prefix)]
        for k in names:
            for s, res in results[k]["solvers"].items():
                c = res["curve"]
                ax.loglog(c["ms"], np.maximum(c["residual"], 1e-14), "-", color=colours[s], lw=0.8,
                          label=s if k == names[0] else None)
        ax.axhline(TOL, color="k", lw=0.6, ls="--")
        ax.set_title(f"{title}: {len(names)}", fontsize=8)
        ax.set_xlabel("ms")
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_ylabel("natural-map residual")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    FIGURES.mkdir(exist_ok=True)
    fig.savefig(FIGURES / "contact_solvers.png", dpi=130)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="problem name prefixes")
    parser.add_argument("--solvers", nargs="*", default=list(SOLVERS))
    parser.add_argument("--scenes", action="store_true", help="only the press plate and liver_press runs")
    parser.add_argument("--methods", nargs="*", default=["auto", "gauss_seidel"], help="with --scenes")
    args = parser.parse_args(argv)
    from tissue import backend

    backend.init()
    info = machine()
    info["openblas_threads"] = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    print_machine(info)
    if args.scenes:
        write_results("contact_solvers_scenes", {"machine": info, "tolerance": TOL, "runs": scene_runs(args.methods)})
        return 0
    paths = sorted(PROBLEMS.glob("*.npz"))
    if not paths:
        print("no problems: run python -m bench.contact_problems first", file=sys.stderr)
        return 2
    results = {}
    for path in paths:
        p = load(path)
        if args.only and not any(p["name"].startswith(o) for o in args.only):
            continue
        entry = {"rows": len(p["q"]), "source": p["source"], "solvers": {}}
        for name in args.solvers:
            res = entry["solvers"][name] = run_solver(p, name)
            print(f"{p['name']:<14}{len(p['q']):>6} rows  {name:<13} {res['iterations']:>5} its  "
                  f"{res['ms']:9.1f} ms ({res['cpu_ms']:.1f} CPU)  residual {res['residual']:.1e} (numpy {res['residual_numpy']:.1e})", flush=True)
        results[p["name"]] = entry
    summary = {}
    for prefix in ("press", "liver450", "stack", "pile", "many"):
        names = [k for k in results if k.startswith(prefix)]
        if names:
            summary[prefix] = {s: {"problems": len(names),
                                   "converged": sum(results[k]["solvers"][s]["converged"] for k in names),
                                   "ms_median": float(np.median([results[k]["solvers"][s]["ms"] for k in names])),
                                   "ms_max": float(np.max([results[k]["solvers"][s]["ms"] for k in names])),
                                   "cpu_ms_max": float(np.max([results[k]["solvers"][s]["cpu_ms"] for k in names])),
                                   "residual_max": float(np.max([results[k]["solvers"][s]["residual"] for k in names]))}
                               for s in args.solvers}
    print("\nper group (time to 1e-6 or the cap: median / max ms, converged):")
    for g, per in summary.items():
        print(f"{g:<10}" + "  ".join(f"{s} {v['ms_median']:.1f}/{v['ms_max']:.1f} ({v['converged']}/{v['problems']})"
                                    for s, v in per.items()))
    write_results("contact_solvers", {"machine": info, "tolerance": TOL, "summary": summary, "problems": results})
    if set(args.solvers) == set(SOLVERS):
        plot(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
