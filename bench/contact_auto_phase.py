"""auto's sweep phase on the press plate, side by side: each contact problem of bench.stability's
press plate cell (every STEP_EVERY-th step, as the stage posed it: W factored or dense, the stage's
warm start) solved with method "auto" under each phase length of large problems
(frictional_contact.AUTO_PHASE_LARGE), alternately in one process, CPU time the best of REPEATS.

    OPENBLAS_NUM_THREADS=1 python -m bench.contact_auto_phase    # ~5 min; bench/results/contact_auto_phase.json

Per phase: the CPU time per solve (median, max, count over 1 s), Newton steps and sweeps together
(median), and the largest natural-map residual, recomputed in numpy from W.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import fields, replace

import numpy as np

from bench.common import machine, print_machine, write_results

PHASES = (16, 4)          # 16: auto's phase on every problem before; 4: on large ones now
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
    from tissue.contact import frictional_contact as fc
    from tissue.contact.frictional_contact import FrictionalContactSolver, natural_map_residual

    info = machine()
    info["openblas_threads"] = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    print_machine(info)
    problems = record_press()
    large = fc.AUTO_PHASE_LARGE
    runs = {phase: [] for phase in PHASES}
    try:
        for p in problems:
            line = []
            for phase in PHASES:
                fc.AUTO_PHASE_LARGE = phase
                best = None
                for _ in range(REPEATS):
                    solver = FrictionalContactSolver(p["W"], p["mu"], method="auto", check=False)
                    start = time.process_time()
                    r, result = solver.solve(p["q"], TOL, 100, p["r0"])
                    cpu = time.process_time() - start
                    best = cpu if best is None else min(best, cpu)
                residual = natural_map_residual(p["W"], p["q"], p["mu"], r)
                runs[phase].append(dict(step=p["step"], rows=len(p["q"]), cpu_s=best, iterations=result.iterations,
                                        residual=residual))
                line.append(f"phase {phase}: {1e3 * best:6.0f} ms CPU, {result.iterations:3d} its, {residual:.1e}")
            print(f"step {p['step']:3d} {len(p['q'])} rows  " + "  |  ".join(line), flush=True)
    finally:
        fc.AUTO_PHASE_LARGE = large
    summary = {}
    for phase, rs in runs.items():
        cpu = np.array([x["cpu_s"] for x in rs])
        summary[phase] = {"problems": len(rs), "cpu_ms_median": float(1e3 * np.median(cpu)),
                          "cpu_ms_max": float(1e3 * cpu.max()), "over_1s": int(np.sum(cpu > 1.0)),
                          "iterations_median": float(np.median([x["iterations"] for x in rs])),
                          "residual_max": float(max(x["residual"] for x in rs))}
        s = summary[phase]
        print(f"phase {phase:2d}: CPU {s['cpu_ms_median']:.0f} ms median, {s['cpu_ms_max']:.0f} max, {s['over_1s']} of "
              f"{s['problems']} over 1 s; iterations {s['iterations_median']:.0f}; residual max {s['residual_max']:.1e}")
    write_results("contact_auto_phase", {"machine": info, "tolerance": TOL, "step_every": STEP_EVERY,
                                         "summary": summary, "problems": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
