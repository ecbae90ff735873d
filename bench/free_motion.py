"""The free motion (implicit Euler and its energy check) per step: ms, Taichi launches and CG
iterations, per scene and setting, with the accuracy each setting's stopping rule leaves.

    python -m bench.free_motion [--steps 80] [--out free_motion]

Scenes: SOFA's floor scene as bench/contact.py builds it (the 596-tet liver on a rigid floor: CG
capped at 25 iterations to 1e-9, no preconditioner, as SOFA's CGLinearSolver), the same with Jacobi
to ‖r‖ ≤ 1e-3 ‖b‖ (a stopping rule CG meets), and `liver_press` (multigrid to 1e-3, two bodies).
Settings, each a simulation of its own, stepped alternately in this process (so the machine's
drift hits all alike): `apart` (the energy check's evaluations in launches of their own, before
this commit's fused check), `fused` (in the serial step's launch) and `fused+warm` (CG started from
the last solves and corrections: CGSettings.warm_start), beside a `converged` run (CG to 1e-12, up to 2,000
iterations) that the others' positions are compared with. Per scene and setting: the median wall ms
of the free-motion stage and the process's CPU ms per whole step (medians over 3 steps in 4), the
Taichi launches per step (every 4th step, counted; all, and the free motion's: its kernels and the
copies of a rejected step's undoing), CG
iterations per solve (median, mean) and the steps at the cap, the largest relative residual CG
reported, the energy check's rejections, and the largest distance of a node from where the
converged run has it, relative to the converged run's largest displacement. The first `--skip`
steps (compiling) are left out of the timings.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from bench import contact as bc
from bench.common import start_on_cpu, write_results

SETTINGS = {"apart": dict(fused=False, warm=False), "fused": dict(fused=True, warm=False),
            "fused+warm": dict(fused=True, warm=True)}
CONVERGED = ["solver.cg_tolerance=1e-12", "solver.cg_iterations=2000"]
# The kernels of the free motion (tissue.solver), and the copies a rejected step's undoing makes.
FREE_MOTION_KERNELS = ("_serial", "_checked_serial", "_energy", "_begin_parallel", "_iterate_parallel",
                       "_end_parallel", "_write_nodes", *bc.LaunchCounter.COPY_KERNELS)


def scenes() -> dict:
    """name -> a function building that scene's simulation with extra overrides."""
    from scenes.liver_press import LiverPress

    def press(overrides):
        return bc.simulation_class()(LiverPress().with_overrides(overrides))

    return {"liver_floor": lambda overrides: bc.floor_scene("warped", overrides=overrides),
            "liver_floor_jacobi": lambda overrides: bc.floor_scene(
                "warped", overrides=["solver.preconditioner=jacobi", "solver.cg_tolerance=1e-3",
                                     "solver.cg_iterations=1000", *overrides]),
            "liver_press": press}


def build(make, setting: dict | None):
    """The scene with a setting (None: the converged run)."""
    if setting is None:
        return make(CONVERGED)
    sim = make([f"solver.cg_warm_start={setting['warm']}"])
    for body in sim.bodies.values():
        body.stepper.fused = setting["fused"]
    return sim


def positions(sim) -> np.ndarray:
    return np.concatenate([body.solver.positions() for body in sim.bodies.values()])


def _counted(step: int, skip: int) -> bool:
    """Whether launches are counted at this step (every 4th after `skip`); the others are timed,
    without the counter's own cost."""
    return step >= skip and step % 4 == 3


def measure(make, steps: int, skip: int) -> dict:
    sims = {name: build(make, setting) for name, setting in SETTINGS.items()}
    sims["converged"] = build(make, None)
    start = positions(sims["converged"])
    deviation = {name: 0.0 for name in SETTINGS}
    displacement = 0.0
    cpu = {name: [] for name in SETTINGS}
    counts = {name: Counter() for name in SETTINGS}
    for step in range(steps):
        for name, sim in (sims.items() if step % 2 == 0 else reversed(sims.items())):
            if name == "converged":
                sim.step()
            elif _counted(step, skip):
                with bc.LaunchCounter() as counter:
                    sim.step()
                counts[name].update(counter.counts)
            else:
                began = time.process_time()
                sim.step()
                cpu[name].append(time.process_time() - began)
        reference = positions(sims["converged"])
        displacement = max(displacement, float(np.abs(reference - start).max()))
        for name in SETTINGS:
            deviation[name] = max(deviation[name], float(np.abs(positions(sims[name]) - reference).max()))
    timed = [step for step in range(skip, steps) if not _counted(step, skip)]
    counted = steps - skip - len(timed)
    out = {}
    for name in SETTINGS:
        sim = sims[name]
        solves = [h for body in sim.bodies.values() for h in (body.solver.stats.history,)]
        iterations = np.concatenate([np.asarray(h["cg_iterations"]) for h in solves])
        residual = np.concatenate([np.asarray(h["cg_residual"]) for h in solves])
        cap = max(body.solver.cg.max_iterations for body in sim.bodies.values())
        launches = counts[name]
        out[name] = {
            "free_motion_ms": 1e3 * float(np.median(np.asarray(sim.stats.times["free_motion"])[timed])),
            "cpu_ms_per_step": 1e3 * float(np.median(np.asarray(cpu[name])[skip:])),
            "launches_per_step": sum(launches.values()) / counted,
            "free_motion_launches_per_step": sum(launches[k] for k in FREE_MOTION_KERNELS) / counted,
            "launches_by_kernel": {k: v / counted for k, v in launches.most_common()},
            "cg_iterations_median": float(np.median(iterations)), "cg_iterations_mean": float(iterations.mean()),
            "cg_solves": int(len(iterations)), "cg_at_cap": int(np.sum(iterations >= cap)),
            "cg_residual_max": float(residual.max()), "cg_residual_median": float(np.median(residual)),
            "energy_rejections": int(sum(np.sum(body.solver.stats.history.get("energy_rejections", []))
                                         for body in sim.bodies.values())),
            "deviation_from_converged": deviation[name] / displacement}
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--skip", type=int, default=3, help="first steps left out of the timings (compiling)")
    parser.add_argument("--scenes", nargs="*", default=None)
    parser.add_argument("--out", default="free_motion", help="the results' name under bench/results")
    args = parser.parse_args(argv)
    info = start_on_cpu()
    results = {}
    for name, make in scenes().items():
        if args.scenes and name not in args.scenes:
            continue
        results[name] = measure(make, args.steps, args.skip)
        print(f"\n{name}: {args.steps} steps ({args.skip} left out of the timings)")
        print(f"{'':<12}{'free ms':>9}{'CPU ms':>9}{'launches':>10}{'free l.':>9}{'CG med':>8}{'CG mean':>9}"
              f"{'at cap':>8}{'res max':>10}{'rejected':>10}{'deviation':>11}")
        for setting, r in results[name].items():
            print(f"{setting:<12}{r['free_motion_ms']:9.2f}{r['cpu_ms_per_step']:9.2f}{r['launches_per_step']:10.1f}"
                  f"{r['free_motion_launches_per_step']:9.1f}{r['cg_iterations_median']:8.0f}"
                  f"{r['cg_iterations_mean']:9.1f}{r['cg_at_cap']:8d}{r['cg_residual_max']:10.1e}"
                  f"{r['energy_rejections']:10d}{r['deviation_from_converged']:11.1e}", flush=True)
    write_results(args.out, {"machine": info, "steps": args.steps, "skip": args.skip, "scenes": results})


if __name__ == "__main__":
    main()
