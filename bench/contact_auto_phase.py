"""auto on the press plate, variants side by side: each contact problem of bench.stability's press
plate cell (every STEP_EVERY-th step, as the stage posed it: W factored or dense, the stage's warm
start) solved with method "auto" under each variant of VARIANTS (settings of tissue.contact.newton
or frictional_contact), alternately in one process, CPU time the best of REPEATS.

    OPENBLAS_NUM_THREADS=1 python -m bench.contact_auto_phase    # ~5 min; bench/results/contact_auto_phase.json

Variants: "reused LU" (GMRES on the solve's last LU once few contacts change state, a fresh LU
otherwise, newton.JACOBI_ITERATIONS = 0: commit ea2594b's solver but for the LU's refinement, which
now stops at the step's forcing) and "diagonal GMRES first",
the default (where no LU serves, GMRES preconditioned by the Newton system's 3×3 diagonal blocks
before a fresh LU; see tissue.contact.newton). The problems include step 1, solved from zero.
(Before, the variants were a fresh LU every Newton step against the reused LU:
commit 00c9082's JSON; auto's sweep phase on large problems, 16 and 4: commit f805f65's.)

Per variant: the CPU time per solve (median, max, count over 1 s), Newton steps and sweeps
together (median), the LUs per solve (median, max), and the largest natural-map residual,
recomputed in numpy from W.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import fields, replace

import numpy as np

from bench.common import machine, print_machine, write_results

VARIANTS = {"reused LU": {"JACOBI_ITERATIONS": 0}, "diagonal GMRES first": {}}
STEP_EVERY = 3
REPEATS = 2
TOL = 1e-6


def record_press() -> list[dict]:
    """The press plate cell's problems, every STEP_EVERY-th step (the last 100-step run's)."""
    from bench import stability
    from bench.contact_problems import Recording
    from tissue.contact import FactoredDelassus

    cell = next(c for c in stability.contact_cells(("polar",)) if c["case"] == "press")
    problems = []

    def keep(index, W, q, mu, r0):
        if index % STEP_EVERY == 0 and len(q) >= 1000:
            # Copies: the stage keeps its dense W in a buffer it reuses the next step.
            W = replace(W, **{f.name: np.copy(getattr(W, f.name)) for f in fields(W)}) \
                if isinstance(W, FactoredDelassus) else np.array(W)
            problems.append(dict(step=index + 1, W=W, q=np.array(q), mu=np.array(mu), r0=np.array(r0)))

    with Recording(keep):
        stability.simulate(cell)
    return problems


def main(argv=None) -> int:
    from tissue import backend

    backend.init()
    from tissue.contact import newton
    from tissue.contact.frictional_contact import FrictionalContactSolver, natural_map_residual

    info = machine()
    info["openblas_threads"] = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    print_machine(info)
    problems = record_press()
    defaults = {name: getattr(newton, name) for settings in VARIANTS.values() for name in settings}
    runs = {variant: [] for variant in VARIANTS}
    # newton factorises through its _lu (LAPACK's getrf called outright), not scipy.linalg.lu_factor
    factors, lu = [], newton._lu

    def counted(J):
        factors.append(len(J))
        return lu(J)

    newton._lu = counted
    try:
        for p in problems:
            line = []
            for variant, settings in VARIANTS.items():
                for name, value in {**defaults, **settings}.items():
                    setattr(newton, name, value)
                best = None
                for _ in range(REPEATS):
                    solver = FrictionalContactSolver(p["W"], p["mu"], method="auto", check=False)
                    factors.clear()
                    start = time.process_time()
                    r, result = solver.solve(p["q"], TOL, 100, p["r0"])
                    cpu = time.process_time() - start
                    best = cpu if best is None else min(best, cpu)
                residual = natural_map_residual(p["W"], p["q"], p["mu"], r)
                lus = sum(k >= 1000 for k in factors)
                runs[variant].append(dict(step=p["step"], rows=len(p["q"]), cpu_s=best, iterations=result.iterations,
                                          lus=lus, residual=residual))
                line.append(f"{variant}: {1e3 * best:5.0f} ms CPU, {result.iterations:3d} its, {lus} LUs, {residual:.1e}")
            print(f"step {p['step']:3d} {len(p['q'])} rows  " + "  |  ".join(line), flush=True)
    finally:
        newton._lu = lu
        for name, value in defaults.items():
            setattr(newton, name, value)
    summary = {}
    for variant, rs in runs.items():
        cpu, lus = np.array([x["cpu_s"] for x in rs]), [x["lus"] for x in rs]
        summary[variant] = {"problems": len(rs), "cpu_ms_median": float(1e3 * np.median(cpu)),
                            "cpu_ms_max": float(1e3 * cpu.max()), "over_1s": int(np.sum(cpu > 1.0)),
                            "iterations_median": float(np.median([x["iterations"] for x in rs])),
                            "lus_median": float(np.median(lus)), "lus_max": int(max(lus)),
                            "residual_max": float(max(x["residual"] for x in rs))}
        s = summary[variant]
        print(f"{variant}: CPU {s['cpu_ms_median']:.0f} ms median, {s['cpu_ms_max']:.0f} max, {s['over_1s']} of "
              f"{s['problems']} over 1 s; iterations {s['iterations_median']:.0f}; LUs {s['lus_median']:.0f} "
              f"(max {s['lus_max']}); residual max {s['residual_max']:.1e}")
    write_results("contact_auto_phase", {"machine": info, "tolerance": TOL, "step_every": STEP_EVERY,
                                         "variants": VARIANTS, "summary": summary, "problems": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
