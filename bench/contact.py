"""Contact benchmark (paper §3.7): ms per step by stage, compliance warping against the exact
compliance (a sparse LU of the current matrix each step: the paper's "50× slower" direct way),
in one run on this machine.

    liver_press   scenes/liver_press.py: the 1,300-tet liver pushed by a probe against 20 capsule
                  ribs and the 800-tet stomach, 200-400 constraint rows (paper: 1,300 tets, up to
                  450 constraints, 70 FPS on an i7 975 including the haptic thread)
    liver_floor   SOFA's contact scene of REFERENCE-TIMINGS.md: the 596-tet liver falls on a rigid
                  floor, μ 0.5, about 28 contacts at rest (SOFA: 1.79 ms/step warped, 5.95 exact)

    python -m bench.contact            # both scenes, both compliances (~2 min on 2 cores)
"""

import argparse
import sys

import numpy as np

from bench.common import machine, print_machine, write_results

SOFA_FLOOR_MS = {"warped": 1.79, "exact": 5.95}
STAGES = ("detection", "constraints", "compliance", "lcp", "correction")


def run_press(compliance: str, steps: int) -> dict:
    from scenes.liver_press import LiverPress
    from tissue.scene import Simulation

    sim = Simulation(LiverPress().with_overrides([f"contact.compliance={compliance}"]))
    return _collect(sim, steps, min_rows=150)


def run_floor(compliance: str, steps: int) -> dict:
    from dataclasses import dataclass, field

    from tissue.contact import Contact, Obstacle
    from tissue.scene import Scene, Simulation, Solver, SoftBody

    @dataclass
    class LiverFloor(Scene):
        dt: float = 0.02
        liver: SoftBody = field(default_factory=lambda: SoftBody(mesh="liver", tets=596, young=3000.0,
                                                                 poisson=0.3, density=1.0))
        floor: Obstacle = field(default_factory=lambda: Obstacle(shape="plane", centre=(0.0, 0.0, -0.035)))
        contact: Contact = field(default_factory=lambda: Contact(friction=0.5, distance=2e-3, tolerance=1e-6,
                                                                 max_iterations=1000, compliance=compliance))
        solver: Solver = field(default_factory=lambda: Solver(cg_iterations=25, cg_tolerance=1e-9))

    return _collect(Simulation(LiverFloor()), steps, min_rows=30)


def _collect(sim, steps: int, min_rows: int) -> dict:
    """Run, then medians over the steps with at least `min_rows` constraint rows."""
    rows, iters = [], []
    for _ in range(steps):
        sim.step()
        rows.append(sim.stats.counters.get("rows", 0))
        iters.append(sim.stats.counters.get("gs_iterations", 0))
    rows, iters = np.array(rows), np.array(iters)
    keep = np.flatnonzero(rows >= min_rows)
    keep = keep[keep >= 3]                     # compile and warm-up
    times = sim.stats.times
    ms = {name: 1e3 * float(np.median(np.asarray(times[name])[keep])) for name in ("free_motion", "contact")}
    ms.update({s: 1e3 * float(np.median(np.asarray(times[f"contact: {s}"])[keep])) for s in STAGES})
    ms["total"] = ms["free_motion"] + ms["contact"]
    return {"ms_per_step": ms, "steps_measured": int(len(keep)), "rows_median": float(np.median(rows[keep])),
            "rows_max": int(rows.max()), "gs_iterations_median": float(np.median(iters[keep])),
            "bodies": {n: {"tets": b.mesh.n_tets, "nodes": b.mesh.n_points} for n, b in sim.bodies.items()}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=80)
    args = parser.parse_args(argv)
    from tissue import backend

    backend.init()
    info = machine()
    print_machine(info)
    out = {"machine": info, "sofa_floor_ms": SOFA_FLOOR_MS}
    for name, run in (("liver_press", run_press), ("liver_floor", run_floor)):
        out[name] = {c: run(c, args.steps) for c in ("warped", "exact")}
        w, e = out[name]["warped"], out[name]["exact"]
        print(f"\n{name}: {w['bodies']}, rows median {w['rows_median']:.0f} (max {w['rows_max']}), "
              f"GS iterations median {w['gs_iterations_median']:.0f}")
        print(f"{'ms/step':<12}" + "".join(f"{k:>13}" for k in ("free_motion",) + STAGES + ("total",)))
        for c in ("warped", "exact"):
            ms = out[name][c]["ms_per_step"]
            print(f"{c:<12}" + "".join(f"{ms[k]:13.2f}" for k in ("free_motion",) + STAGES + ("total",)))
        ratio = e["ms_per_step"]["contact"] / w["ms_per_step"]["contact"]
        out[name]["exact_over_warped_contact"] = ratio
        print(f"contact stage: exact / warped = {ratio:.1f}x")
    write_results("contact", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
