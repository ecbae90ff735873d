"""Contact benchmark (paper §3.7): ms per step by stage, compliance warping against the exact
compliance (a sparse Cholesky of the current matrix each step, CHOLMOD: the paper's "50× slower"
direct way, as SOFA's LDLᵀ; and scipy's LU, its fallback without scikit-sparse, in the same run),
and the contact-force error between the two, in one run on this machine.

    liver_press   scenes/liver_press.py: the 1,300-tet liver pushed by a probe into the 800-tet
                  stomach, its right lobe against 20 capsule ribs; 300-380 constraint rows while
                  pressed (paper: 1,300 tets, up to 450 constraints, 70 FPS on an i7 975 with the
                  haptic thread). Per stage the median over the pressed steps (≥ 150 rows), the
                  Taichi kernel launches per step, and along the warped run, every 8th pressed
                  step, the exact W of the same rows and both frictional problems solved: the
                  error of the warped contact forces.
    450 rows      the same scene with the alarm distance widened to 4 mm (about 450 rows while
                  pressed): per stage, and every 4th step with ≥ 420 rows the exact W of the same
                  rows (Cholesky of this step's matrix, solves, H A⁻¹ Hᵀ; and by LU) against W by warping, formed
                  densely (the paper's kernels) and as the stage keeps it (its factors), ms and
                  ratios, and the force error there; then the run again with W formed
                  (contact.delassus=dense): the stages side by side; and the run twice more,
                  stepped alternately, Gauss-Seidel on the contacts in play (default) against
                  always on the whole problem.
    row bands     per stage, the medians over the steps of both runs above with about 100 (50-170), 250 and
                  450-500 constraint rows (the press's approach, its default, the wide alarm).
    Gauss-Seidel  the frictional problems of the 450-row run (every 8th step with ≥ 420 rows),
                  solved again with sweep caps 1, 2, 4, ... 512 by plain and by Anderson-accelerated
                  Gauss-Seidel, and by Anderson on the contacts in play alone (`reduce`):
                  natural-map residual against sweeps and against time (figures/contact_gauss_seidel.png).
    liver_floor   SOFA's contact scene of REFERENCE-TIMINGS.md: the 596-tet liver falls on a rigid
                  floor, μ 0.5, about 28 contacts at rest (SOFA: 1.79 ms/step warped, 5.95 exact);
                  warped, exact (Cholesky) and exact by LU (exact_lu)

    python -m bench.contact            # everything (~40 s on 2 cores)
    python -m bench.contact --quick    # liver_press warped only, and the 450-row comparison
    python -m bench.contact --floor    # the floor scene's step taken apart (stages, launches, copies)
    python -m bench.contact --press-profile   # the same for liver_press
    python -m bench.contact --press-sampled   # liver_press's CPU by part of the step, sampled on CPU time
"""

import argparse
import sys
import time
from collections import Counter
from contextlib import contextmanager

import numpy as np

from bench.common import machine, print_machine, write_results

SOFA_FLOOR_MS = {"warped": 1.79, "exact": 5.95}
STAGES = ("detection", "constraints", "compliance", "lcp", "correction")
WIDE_DISTANCE = 4e-3     # m: liver_press's alarm distance widened to about 450 rows
BANDS = {"~100": (50, 170), "~250": (200, 300), "450-500": (420, 520)}   # constraint rows
CAPS = [2 ** k for k in range(10)]                                      # Gauss-Seidel sweep caps
GS_VARIANTS = (("plain", False, False), ("anderson", True, False), ("anderson, in play", True, True))  # (name, Anderson, reduce)


class LaunchCounter:
    """Counts Taichi kernel launches by kernel name while active: launches through Taichi
    (Kernel.__call__) and those replayed by tissue.launch (whose first, recording launch counts
    once); and the numpy<->device copies: numpy arrays handed to a kernel (`numpy_arguments`: on
    the CPU read in place, but set argument by argument, 15-30 µs each; elsewhere a transfer each)
    and Taichi's from_numpy / to_numpy copy kernels (`copies`, among the launches too); and each
    counted launch's wall time from the Python call to its return (`seconds`, by kernel: argument
    setting or replay, and the kernel's work; CPU launches return when done)."""

    COPY_KERNELS = ("ext_arr_to_ndarray", "ndarray_to_ext_arr", "ext_arr_to_ndarray_matrix",
                    "ndarray_matrix_to_ext_arr")

    def __enter__(self):
        from taichi.lang import kernel_impl

        from tissue import launch

        self.counts, self.numpy_arguments, self.paused = Counter(), 0, False
        self.seconds = {}
        self._patched = [(kernel_impl.Kernel, kernel_impl.Kernel.__call__), (launch.Replayed, launch.Replayed.__call__)]
        taichi_call, replay_call = (original for _, original in self._patched)
        counter, inside = self, [False]

        def timed(name, launch):
            start = time.perf_counter()
            try:
                return launch()
            finally:
                counter.seconds.setdefault(name, []).append(time.perf_counter() - start)

        def call(kernel, *args, **kwargs):
            if counter.paused or inside[0]:
                return taichi_call(kernel, *args, **kwargs)
            counter.counts[kernel.func.__name__] += 1
            counter.numpy_arguments += sum(isinstance(a, np.ndarray) for a in args)
            return timed(kernel.func.__name__, lambda: taichi_call(kernel, *args, **kwargs))

        def replay(replayed, *args):
            inside[0] = True
            try:
                if counter.paused:
                    return replay_call(replayed, *args)
                counter.counts[replayed.primal.func.__name__] += 1
                return timed(replayed.primal.func.__name__, lambda: replay_call(replayed, *args))
            finally:
                inside[0] = False

        kernel_impl.Kernel.__call__, launch.Replayed.__call__ = call, replay
        return self

    @property
    def copies(self) -> int:
        return sum(self.counts[k] for k in self.COPY_KERNELS)

    def __exit__(self, *exc):
        for owner, original in self._patched:
            owner.__call__ = original


@contextmanager
def factorization(kind: str):
    """ExactCompliance built inside takes `kind` ("cholmod" or "lu": scipy's LU, as without
    scikit-sparse) for "auto"."""
    import tissue.contact.compliance as compliance

    original = compliance._cholmod
    if kind == "lu":
        compliance._cholmod = None
    try:
        yield
    finally:
        compliance._cholmod = original


def simulation_class():
    """`tissue.simulation.Simulation`; `bench.contact_versus` also runs this file in checkouts from
    before it moved out of `tissue.scene`. `tissue.scene` is asked first: in an old checkout,
    `tissue.simulation` would be found all the same, in the main checkout that the virtual
    environment installs in editable mode (its finder maps the package's missing modules there)."""
    try:
        from tissue.scene import Simulation
    except ImportError:
        from tissue.simulation import Simulation
    return Simulation


def press(compliance: str, overrides=()):
    from scenes.liver_press import LiverPress

    return simulation_class()(LiverPress().with_overrides([f"contact.compliance={compliance}", *overrides]))


def contact_stage(sim):
    return next(s for s in sim.stages if s.name == "contact").stage


def force_error(solve, W_warped, W_exact, rows, contacts, mu) -> dict:
    """Both frictional problems of one state solved by the stage's `solve` to its tolerance (same
    q, μ, warm start): relative errors of the contact forces and of their sum, and of W."""
    lam_w, _ = solve(W_warped, rows, contacts, mu)
    lam_e, _ = solve(W_exact, rows, contacts, mu)
    nc = rows.n_contacts
    fw = np.einsum("ki,kij->kj", lam_w[:3 * nc].reshape(-1, 3), rows.frames)
    fe = np.einsum("ki,kij->kj", lam_e[:3 * nc].reshape(-1, 3), rows.frames)
    return {"forces": float(np.linalg.norm(fw - fe) / np.linalg.norm(fe)),
            "total_force": float(np.linalg.norm(fw.sum(0) - fe.sum(0)) / np.linalg.norm(fe.sum(0))),
            "W": float(np.linalg.norm(W_warped - W_exact) / np.linalg.norm(W_exact))}


def exact_W(stage, rows, kind: str = "auto") -> np.ndarray:
    """h H A⁻¹ Hᵀ with A the matrix of this step's free motion (the solver's own blocks)."""
    from tissue.contact.compliance import ExactCompliance

    W = np.zeros((rows.n_rows, rows.n_rows))
    for b in np.unique(rows.body):
        c = ExactCompliance(stage.bodies[b].solver, factorization=kind)
        c.factorise()
        c.prepare(rows, int(b))
        c.add_to(W)
    return W


def warped_W(stage, rows) -> tuple[np.ndarray, float]:
    """W = h (H R) A₀⁻¹ (H R)ᵀ formed densely by the warping kernels (the paper's kernels 1 and 2,
    from this step's rotations), and its ms: what the exact compliance is set against. (The stage
    itself keeps W's factors and never forms it.)"""
    from tissue.contact.constraints import JaggedDiagonal

    W = np.zeros((rows.n_rows, rows.n_rows))
    start = time.perf_counter()
    for b in np.unique(rows.body):
        c = stage.compliance[b]
        c.prepare(JaggedDiagonal(rows, int(b)))
        c.add_to(W)
    return W, 1e3 * (time.perf_counter() - start)


def run_press(compliance: str, steps: int, check_every: int = 0, min_rows: int = 150,
              overrides=(), problems=None) -> dict:
    """The scene stepped `steps` times. With check_every: every that many steps with at least
    `min_rows` rows, the exact W of the same rows (timed) and the force error of the warped one,
    on the side (the run itself goes on with its own W). `problems` (a list): gets the frictional
    problems (W, q, μ, warm start) of the checked steps, as the stage posed them."""
    sim = press(compliance, overrides)
    stage = contact_stage(sim)
    checks, checked_steps = [], set()
    launches = LaunchCounter()
    if check_every:
        solve, seen = stage._solve, [0]

        def checked(W, rows, contacts, mu, keys=None):
            if rows.n_rows >= min_rows:
                seen[0] += 1
                if seen[0] % check_every == 0:       # (left out of the timings and launch counts)
                    launches.paused = True
                    checked_steps.add(len(sim.stats.times["contact"]))
                    start = time.perf_counter()
                    W_exact = exact_W(stage, rows)
                    exact_ms = 1e3 * (time.perf_counter() - start)
                    start = time.perf_counter()
                    exact_W(stage, rows, "lu")
                    exact_lu_ms = 1e3 * (time.perf_counter() - start)
                    W_warped, dense_ms = warped_W(stage, rows)
                    check = force_error(solve, W_warped, W_exact, rows, contacts, mu)
                    check.update(rows=rows.n_rows, exact_ms=exact_ms, exact_lu_ms=exact_lu_ms, warped_dense_ms=dense_ms,
                                 warped_ms=1e3 * stage.stats.times["compliance"][-1])
                    checks.append(check)
                    if problems is not None:
                        problems.append(posed(W, rows, contacts, mu))
                    launches.paused = False
            return solve(W, rows, contacts, mu, keys)

        stage._solve = checked
        posed = _posed(solve)
    for _ in range(3):
        sim.step()
    with launches:
        result = _collect(sim, steps - 3, min_rows=min_rows, skip=checked_steps)
    result["launches_per_step"] = sum(launches.counts.values()) / (steps - 3)
    result["launches_by_kernel"] = {k: v / (steps - 3) for k, v in launches.counts.most_common()}
    if checks:
        result["checks"] = {k: {"median": float(np.median([c[k] for c in checks])),
                                "max": float(np.max([c[k] for c in checks]))} for k in checks[0]}
        result["checks"]["states"] = len(checks)
    return result


def _posed(solve):
    """A function (W, rows, contacts, μ) -> the frictional problem the stage's `solve` poses."""
    import tissue.contact.pipeline as pipeline

    def posed(W, rows, contacts, mu):
        got = []

        class Recorder(pipeline.FrictionalContactSolver):
            def solve(self, q, tol=1e-6, max_iterations=1000, r0=None):
                W = self.W.toarray() if isinstance(self.W, pipeline.FactoredDelassus) else self.W.copy()
                got.append((W, np.array(q), self.mu.copy(), np.array(r0)))
                return super().solve(q, tol, 0, r0)

        original, pipeline.FrictionalContactSolver = pipeline.FrictionalContactSolver, Recorder
        try:
            solve(W, rows, contacts, mu)
        finally:
            pipeline.FrictionalContactSolver = original
        return got[0]

    return posed


def floor_scene(compliance: str = "warped", step_control: str | None = None, overrides=()):
    """SOFA's floor scene (REFERENCE-TIMINGS.md): the 596-tet liver dropped on a rigid floor,
    μ 0.5; `step_control` overrides the solver's (the scene's default: energy control), and
    `overrides` ("solver.preconditioner=jacobi", ...) any field."""
    from dataclasses import dataclass, field

    from tissue.contact import Contact, Obstacle
    from tissue.scene import Scene, Solver, SoftBody

    Simulation = simulation_class()

    solver = dict(cg_iterations=25, cg_tolerance=1e-9)
    if step_control is not None:
        solver["step_control"] = step_control

    @dataclass
    class LiverFloor(Scene):
        dt: float = 0.02
        liver: SoftBody = field(default_factory=lambda: SoftBody(mesh="liver", tets=596, young=3000.0,
                                                                 poisson=0.3, density=1.0))
        floor: Obstacle = field(default_factory=lambda: Obstacle(shape="plane", centre=(0.0, 0.0, -0.035)))
        contact: Contact = field(default_factory=lambda: Contact(friction=0.5, distance=2e-3, tolerance=1e-6,
                                                                 max_iterations=1000, compliance=compliance))
        solver: Solver = field(default_factory=lambda: Solver(**solver))

    return Simulation(LiverFloor().with_overrides(list(overrides)))


def run_floor(compliance: str, steps: int) -> dict:
    sim = floor_scene(compliance)
    for _ in range(3):
        sim.step()
    return _collect(sim, steps - 3, min_rows=30)


def step_profile(sim, steps: int = 100, settle: int = 40) -> dict:
    """One contact step of `sim` taken apart, after `settle` steps (the floor scene at rest, the
    press pressed): medians of each stage's wall ms (free motion, the contact stage's five stages,
    and the Python between them, `glue`: the contact stage less its stages), CPU ms of a whole
    step, kernel launches per step by kernel (free motion and contact stage apart; replayed ones
    included) and each kernel's median wall ms per launch, numpy arrays handed to kernels and
    from_numpy/to_numpy copies per step, and the contact stage's most costly Python functions by
    own time (cProfile, another `steps` steps: the profiler inflates small calls, so read them as
    a ranking)."""
    import cProfile
    import pstats

    for _ in range(settle):
        sim.step()
    layer = next(s for s in sim.stages if s.name == "contact")
    counts = {"free_motion": Counter(), "contact": Counter()}
    numpy_args = {"free_motion": 0, "contact": 0}
    counter = LaunchCounter()
    original = layer.step

    def counted(sim_):
        inner = Counter(counter.counts), counter.numpy_arguments
        original(sim_)
        counts["contact"].update(counter.counts - inner[0])
        numpy_args["contact"] += counter.numpy_arguments - inner[1]

    layer.step = counted
    cpu = []
    with counter:
        for _ in range(steps):
            start = time.process_time()
            sim.step()
            cpu.append(time.process_time() - start)
    del layer.step
    total = Counter(counter.counts)
    counts["free_motion"] = total - counts["contact"]
    numpy_args["free_motion"] = counter.numpy_arguments - numpy_args["contact"]
    times = {k: 1e3 * np.asarray(v[settle:]) for k, v in sim.stats.times.items()}
    ms = {"free_motion": float(np.median(times["free_motion"]))}
    ms.update({s: float(np.median(times[f"contact: {s}"])) for s in STAGES})
    ms["glue"] = float(np.median(times["contact"] - sum(times[f"contact: {s}"] for s in STAGES)))
    ms["contact"] = float(np.median(times["contact"]))
    profile = cProfile.Profile()

    def profiled(sim_):
        profile.enable()
        try:
            original(sim_)
        finally:
            profile.disable()

    layer.step = profiled
    for _ in range(steps):
        sim.step()
    del layer.step
    entries = pstats.Stats(profile).stats
    top = sorted(entries.items(), key=lambda kv: -kv[1][2])[:15]
    functions = [{"function": f"{path.split('site-packages/')[-1].split('/work/')[-1]}:{line}({name})",
                  "calls_per_step": n / steps, "own_ms_per_step": 1e3 * own / steps}
                 for (path, line, name), (_, n, own, _cum, _) in top]
    copies = {k: sum(c[name] for name in LaunchCounter.COPY_KERNELS) for k, c in counts.items()}
    return {"ms_per_step": ms, "cpu_ms_per_step": 1e3 * float(np.median(cpu)),
            "rows_median": float(np.median(sim.stats.history["rows"][settle:])),
            "launches_per_step": {k: sum(c.values()) / steps for k, c in counts.items()},
            "launches_by_kernel": {k: {n: v / steps for n, v in c.most_common()} for k, c in counts.items()},
            "launch_ms_median": {n: 1e3 * float(np.median(t)) for n, t in counter.seconds.items()},
            "numpy_arguments_per_step": {k: v / steps for k, v in numpy_args.items()},
            "copies_per_step": {k: v / steps for k, v in copies.items()},
            "python_functions": functions}


def cpu_sampled(simulations: int = 16, settle: int = 8, steps: int = 72) -> dict:
    """Where liver_press's pressed steps spend their CPU: a profile sampled on the process's CPU
    time (ITIMER_PROF: the stack at each tick of CPU, ~4 ms here), over `steps` steps after `settle`
    of each of `simulations` simulations. A wall-clock sampler would charge the time other jobs
    hold the cores to whatever line was running; cProfile inflates the many small calls. Per part
    of the step, CPU ms a step (the mean step) in the kernels (samples whose innermost Python frame
    is a launch's) and on the host: the free motion, Newton's iterations, and the contact stage by
    the call its step made (Python takes a signal at its next check, so a sample at the end of one
    call may be charged to the next)."""
    import signal

    samples, active = [], [False]

    def sample(_signal, frame):
        if active[0]:
            stack = []
            while frame is not None:
                stack.append((frame.f_code.co_filename, frame.f_code.co_name))
                frame = frame.f_back
            samples.append(stack)

    previous = signal.signal(signal.SIGPROF, sample)
    cpu = 0.0
    try:
        for _ in range(simulations):
            sim = press("warped")
            for _ in range(settle):
                sim.step()
            signal.setitimer(signal.ITIMER_PROF, 1e-3, 1e-3)
            start, active[0] = time.process_time(), True
            for _ in range(steps):
                sim.step()
            active[0] = False
            cpu += time.process_time() - start
            signal.setitimer(signal.ITIMER_PROF, 0, 0)
    finally:
        signal.signal(signal.SIGPROF, previous)
    parts, kernels = Counter(), Counter()
    for stack in samples:
        part = _sampled_part(stack)
        parts[part] += 1
        path, name = stack[0]                   # in a launch: the Python frame that made it (Taichi's or a replay)
        kernels[part] += name in ("launch_kernel", "__call__") and path.endswith(("launch.py", "kernel_impl.py"))
    ms = 1e3 * cpu / (simulations * steps) / max(1, len(samples))      # a sample's share of a step
    return {"cpu_ms_per_step": 1e3 * cpu / (simulations * steps), "samples": len(samples),
            "parts": {part: {"kernels_ms": ms * kernels[part], "host_ms": ms * (n - kernels[part])}
                      for part, n in parts.most_common()}}


def _sampled_part(stack) -> str:
    """The part of a step a sampled stack (innermost first) is in (see cpu_sampled)."""
    if any(path.endswith("contact/newton.py") for path, _ in stack):
        return "contact: Newton"
    outer = stack[::-1]
    at = next((i for i, (path, name) in enumerate(outer) if name == "step" and path.endswith("contact/pipeline.py")),
              None)
    if at is None:
        in_layer = any(name == "step" and path.endswith("contact/layer.py") for path, name in stack)
        return "contact: the layer (energy budget)" if in_layer else "free motion"
    return "contact: " + (outer[at + 1][1] if at + 1 < len(outer) else "its step")


def print_step_profile(p: dict, title: str) -> None:
    ms = p["ms_per_step"]
    print(f"\n{title}: rows {p['rows_median']:.0f}, CPU {p['cpu_ms_per_step']:.2f} ms/step; wall ms/step "
          + ", ".join(f"{k} {v:.3f}" for k, v in ms.items()))
    for part in ("free_motion", "contact"):
        print(f"  {part}: {p['launches_per_step'][part]:.1f} launches/step ("
              + ", ".join(f"{k} {v:.1f} × {p['launch_ms_median'][k]:.3f} ms"
                          for k, v in p["launches_by_kernel"][part].items())
              + f"); numpy arguments {p['numpy_arguments_per_step'][part]:.1f}, copies {p['copies_per_step'][part]:.1f}")
    print("  contact stage, own time by function (cProfile):")
    for f in p["python_functions"][:10]:
        print(f"    {f['own_ms_per_step']:7.3f} ms  {f['calls_per_step']:5.1f} calls  {f['function']}")


def _collect(sim, steps: int, min_rows: int, skip=()) -> dict:
    """Run, then medians over the steps with at least `min_rows` constraint rows (leaving out the
    steps numbered in `skip`, counted from the simulation's first)."""
    start = len(sim.stats.times["contact"])
    rows, iters = [], []
    for _ in range(steps):
        sim.step()
        rows.append(sim.stats.counters.get("rows", 0))
        iters.append(sim.stats.counters.get("gs_iterations", 0))
    rows, iters = np.array(rows), np.array(iters)
    keep = np.flatnonzero((rows >= min_rows) & ~np.isin(np.arange(steps) + start, list(skip)))
    times = {k: np.asarray(v[start:]) for k, v in sim.stats.times.items()}
    ms = {name: 1e3 * float(np.median(times[name][keep])) for name in ("free_motion", "contact")}
    ms.update({s: 1e3 * float(np.median(times[f"contact: {s}"][keep])) for s in STAGES})
    ms["total"] = 1e3 * float(np.median((times["free_motion"] + times["contact"])[keep]))
    valid = np.ones(steps, bool)
    valid[np.isin(np.arange(steps) + start, list(skip))] = False
    per_step = {name: 1e3 * times[name][valid] for name in ("free_motion", "contact")}
    per_step.update({s: 1e3 * times[f"contact: {s}"][valid] for s in STAGES})
    per_step.update(rows=rows[valid], gs_iterations=iters[valid])
    return {"ms_per_step": ms, "steps_measured": int(len(keep)), "rows_median": float(np.median(rows[keep])),
            "rows_max": int(rows.max()), "gs_iterations_median": float(np.median(iters[keep])),
            "bodies": {n: {"tets": b.mesh.n_tets, "nodes": b.mesh.n_points} for n, b in sim.bodies.items()},
            "per_step": per_step}


def reduce_side_by_side(steps: int, min_rows: int = 420) -> dict:
    """The 450-row press twice with method 'gauss_seidel', stepped alternately in this process:
    Gauss-Seidel on the contacts in play after a step of many sweeps (the stage's rule,
    pipeline.REDUCE_ABOVE) against always on the whole problem ('auto' always sweeps the whole). LCP ms, sweeps and residual, medians over the steps with at least
    `min_rows` rows in both runs."""
    import tissue.contact.pipeline as pipeline

    default = pipeline.REDUCE_ABOVE
    runs = {"in play": default, "whole": 10 ** 9}
    sims = {name: press("warped", [f"contact.distance={WIDE_DISTANCE}", "contact.method=gauss_seidel"])
            for name in runs}
    try:
        for _ in range(steps):
            for name, sim in sims.items():
                pipeline.REDUCE_ABOVE = runs[name]
                sim.step()
    finally:
        pipeline.REDUCE_ABOVE = default
    stats = {name: contact_stage(sim).stats for name, sim in sims.items()}
    keep = np.ones(steps, bool)
    for st in stats.values():
        keep &= np.array(st.history["rows"]) >= min_rows
    out = {"steps": int(keep.sum())}
    for name, st in stats.items():
        out[name] = {"lcp_ms": 1e3 * float(np.median(np.array(st.times["lcp"])[keep])),
                     "sweeps": float(np.median(np.array(st.history["gs_iterations"])[keep])),
                     "residual_max": float(np.max(np.array(st.history["gs_residual"])[keep]))}
    return out


def row_bands(*runs) -> dict:
    """Per stage, the median ms over the steps of `runs` whose row count falls in each band."""
    steps = {k: np.concatenate([r["per_step"][k] for r in runs]) for k in runs[0]["per_step"]}
    out = {}
    for band, (lo, hi) in BANDS.items():
        sel = (steps["rows"] >= lo) & (steps["rows"] < hi)
        if sel.any():
            ms = {k: float(np.median(steps[k][sel])) for k in ("free_motion",) + STAGES}
            ms["total"] = float(np.median(steps["free_motion"][sel] + steps["contact"][sel]))
            out[band] = {"steps": int(sel.sum()), "rows_median": float(np.median(steps["rows"][sel])),
                         "gs_iterations_median": float(np.median(steps["gs_iterations"][sel])), "ms_per_step": ms}
    return out


def gauss_seidel_curves(problems) -> dict:
    """Residual and time against the sweep cap, plain and Anderson-accelerated Gauss-Seidel, and
    Anderson on the contacts in play (`reduce`), on the stage's own (scaled) problems with their
    warm starts; medians over the problems."""
    from tissue.contact.frictional_contact import ANDERSON_WINDOW, FrictionalContactSolver

    out = {}
    for name, anderson, reduce in GS_VARIANTS:
        res, ms, its = [], [], []
        for W, q, mu, r0 in problems:
            solver = FrictionalContactSolver(W, mu, anderson=ANDERSON_WINDOW if anderson else 0, check=False,
                                             reduce=reduce)
            solver.solve(q, 1e-6, 1, r0=r0)                       # compile and warm up
            row = [min((solver.solve(q, 1e-12, cap, r0=r0)[1] for _ in range(3)), key=lambda i: i.time_s)
                   for cap in CAPS]
            res.append([i.residual for i in row])
            ms.append([1e3 * i.time_s for i in row])
            its.append(solver.solve(q, 1e-6, 10_000, r0=r0)[1].iterations)
        out[name] = {"caps": CAPS, "residual": np.median(res, axis=0).tolist(), "ms": np.median(ms, axis=0).tolist(),
                     "sweeps_to_1e-6": {"median": float(np.median(its)), "max": int(np.max(its))}}
    out["problems"], out["rows_median"] = len(problems), float(np.median([len(p[1]) for p in problems]))
    return out


def plot_gauss_seidel(curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.common import FIGURES

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    for (name, *_), style in zip(GS_VARIANTS, ("o-", "s-", "^-")):
        c = curves[name]
        label = f"{name} (to 1e-6: {c['sweeps_to_1e-6']['median']:.0f} sweeps, median)"
        axes[0].loglog(c["caps"], c["residual"], style, label=label, ms=3)
        axes[1].loglog(c["ms"], c["residual"], style, label=name, ms=3)
    for ax in axes:
        ax.axhline(1e-6, color="grey", lw=0.8, ls="--")
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_xlabel("Gauss-Seidel sweeps")
    axes[1].set_xlabel("time (ms)")
    axes[0].set_ylabel("natural-map residual")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"liver_press, {curves['problems']} frictional problems of ~{curves['rows_median']:.0f} rows "
                 "(warm-started)", fontsize=9)
    fig.tight_layout()
    FIGURES.mkdir(exist_ok=True)
    fig.savefig(FIGURES / "contact_gauss_seidel.png", dpi=130)
    plt.close(fig)


def _table(name: str, results: dict) -> None:
    first = next(iter(results.values()))
    print(f"\n{name}: {first['bodies']}, rows median {first['rows_median']:.0f} (max {first['rows_max']}), "
          f"GS iterations median {first['gs_iterations_median']:.0f}")
    cols = ("free_motion",) + STAGES + ("total",)
    print(f"{'ms/step':<12}" + "".join(f"{k:>13}" for k in cols) + f"{'launches':>10}")
    for c, r in results.items():
        ms = r["ms_per_step"]
        launches = f"{r['launches_per_step']:10.1f}" if "launches_per_step" in r else ""
        print(f"{c:<12}" + "".join(f"{ms[k]:13.2f}" for k in cols) + launches)


def _errors(c: dict, where: str) -> None:
    print(f"warped vs exact W, {where} ({c['states']} states, same rows, each LCP solved to tolerance): "
          f"‖ΔW‖/‖W‖ median {c['W']['median']:.3f} (max {c['W']['max']:.3f}); contact forces "
          f"{c['forces']['median']:.3f} ({c['forces']['max']:.3f}); their sum {c['total_force']['median']:.3f} "
          f"({c['total_force']['max']:.3f})")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--quick", action="store_true", help="liver_press warped and the 450-row comparison only")
    parser.add_argument("--floor", action="store_true", help="the floor scene's step taken apart only")
    parser.add_argument("--press-profile", action="store_true", help="liver_press's step taken apart only")
    parser.add_argument("--press-sampled", action="store_true",
                        help="liver_press's pressed steps' CPU by part, sampled on CPU time only")
    parser.add_argument("--out", help="the results' name under bench/results (default: contact, contact-quick, "
                        "contact-floor, contact-press or contact-press-sampled, by mode; a name of your own keeps "
                        "the committed ones)")
    args = parser.parse_args(argv)
    from tissue import backend

    backend.init()
    info = machine()
    print_machine(info)
    out = {"machine": info, "sofa_floor_ms": SOFA_FLOOR_MS}
    if args.floor:
        for name, control in (("energy control (default)", None), ("no step control", "none")):
            out[name] = step_profile(floor_scene("warped", control))
            print_step_profile(out[name], f"liver_floor, warped, {name}")
        write_results(args.out or "contact-floor", out)
        return 0
    if args.press_sampled:
        out["liver_press"] = sampled = cpu_sampled()
        print(f"liver_press: {sampled['cpu_ms_per_step']:.2f} CPU ms a step (mean), {sampled['samples']} samples")
        for part, v in sampled["parts"].items():
            print(f"  {v['kernels_ms'] + v['host_ms']:6.3f} ms: kernels {v['kernels_ms']:6.3f}, host {v['host_ms']:6.3f}  {part}")
        write_results(args.out or "contact-press-sampled", out)
        return 0
    if args.press_profile:
        # both passes within the scene's 80 steps (3.2 s), pressed from the start (195-380 rows)
        out["liver_press"] = step_profile(press("warped"), steps=37, settle=5)
        print_step_profile(out["liver_press"], "liver_press, warped")
        write_results(args.out or "contact-press", out)
        return 0

    press_results = {"warped": run_press("warped", args.steps, check_every=0 if args.quick else 8)}
    if not args.quick:
        press_results["exact"] = run_press("exact", args.steps)
        with factorization("lu"):
            press_results["exact_lu"] = run_press("exact", args.steps)
    out["liver_press"] = press_results
    _table("liver_press", press_results)
    if "exact" in press_results:
        w, e = press_results["warped"]["ms_per_step"], press_results["exact"]["ms_per_step"]
        lu = press_results["exact_lu"]["ms_per_step"]
        out["liver_press"]["exact_over_warped"] = {"compliance": e["compliance"] / w["compliance"],
                                                   "contact": e["contact"] / w["contact"],
                                                   "compliance_lu": lu["compliance"] / w["compliance"]}
        print(f"exact / warped: compliance stage {e['compliance'] / w['compliance']:.0f}x (by LU "
              f"{lu['compliance'] / w['compliance']:.0f}x), contact stage {e['contact'] / w['contact']:.0f}x")
    if "checks" in press_results["warped"]:
        _errors(press_results["warped"]["checks"], "along the warped run")
    calls = press_results["warped"]["launches_by_kernel"]
    print("kernel launches per step (warped): " + ", ".join(f"{k} {v:.1f}" for k, v in calls.items()))

    # The paper's 450 constraints: the same scene with a wider alarm distance (more contact points).
    problems = []
    wide = run_press("warped", 72, check_every=4, min_rows=420, overrides=[f"contact.distance={WIDE_DISTANCE}"],
                     problems=problems)
    out["liver_press_450_rows"] = wide
    if "checks" in wide:
        c = wide["checks"]
        print(f"\nliver_press, alarm distance {1e3 * WIDE_DISTANCE:.1f} mm: rows median {wide['rows_median']:.0f} "
              f"(max {wide['rows_max']}); total {wide['ms_per_step']['total']:.2f} ms/step, compliance "
              f"{wide['ms_per_step']['compliance']:.2f}, lcp {wide['ms_per_step']['lcp']:.2f}")
        print(f"W at {c['rows']['median']:.0f} rows: exact {c['exact_ms']['median']:.1f} ms (Cholesky and solves; "
              f"by LU {c['exact_lu_ms']['median']:.1f}); "
              f"warped, formed densely {c['warped_dense_ms']['median']:.2f} ms: exact / warped = "
              f"{c['exact_ms']['median'] / c['warped_dense_ms']['median']:.0f}x; the stage's compliance (W's "
              f"factors) {c['warped_ms']['median']:.2f} ms: "
              f"{c['exact_ms']['median'] / c['warped_ms']['median']:.0f}x")
        _errors(c, "at ≥ 420 rows")

    # The same 450-row run with W formed (the paper's kernel 2, dense Gauss-Seidel) instead of
    # kept as its factors: the stages that differ, side by side in this run.
    # (With the same side checks as the run above, so that both runs' caches see the same.)
    dense = run_press("warped", 72, check_every=4, min_rows=420,
                      overrides=[f"contact.distance={WIDE_DISTANCE}", "contact.delassus=dense"])
    out["liver_press_450_rows_dense_W"] = dense
    _table("liver_press, 450 rows: W's factors against W formed", {"factors": wide, "dense W": dense})
    f, d = wide["ms_per_step"], dense["ms_per_step"]
    print(f"dense W / factors: compliance {d['compliance'] / f['compliance']:.2f}x, lcp {d['lcp'] / f['lcp']:.2f}x, "
          f"contact stage {d['contact'] / f['contact']:.2f}x")
    if "checks" in wide:
        exact_ms, lu_ms = wide["checks"]["exact_ms"]["median"], wide["checks"]["exact_lu_ms"]["median"]
        out["exact_over_warped_450_rows"] = {"factors": exact_ms / f["compliance"], "dense_W": exact_ms / d["compliance"],
                                             "factors_lu": lu_ms / f["compliance"], "dense_W_lu": lu_ms / d["compliance"]}
        print(f"exact W ({exact_ms:.1f} ms; by LU {lu_ms:.1f}) / the warped compliance stage: factors "
              f"{exact_ms / f['compliance']:.0f}x (LU {lu_ms / f['compliance']:.0f}x), W formed "
              f"{exact_ms / d['compliance']:.0f}x (LU {lu_ms / d['compliance']:.0f}x)")

    ab = reduce_side_by_side(72)
    out["liver_press_450_rows_in_play"] = ab
    print(f"Gauss-Seidel at ≥ 420 rows, two runs stepped alternately ({ab['steps']} steps): on the contacts in play "
          f"(default) {ab['in play']['lcp_ms']:.2f} ms, {ab['in play']['sweeps']:.0f} sweeps; always on the whole "
          f"problem {ab['whole']['lcp_ms']:.2f} ms, {ab['whole']['sweeps']:.0f} sweeps (median lcp stage)")

    bands = row_bands(press_results["warped"], wide)
    out["row_bands"] = bands
    print(f"\nwarped, by constraint rows (medians, ms/step):\n{'rows':<9}{'steps':>6}{'GS it':>7}"
          + "".join(f"{k:>13}" for k in ("free_motion",) + STAGES + ("total",)))
    for band, b in bands.items():
        print(f"{band:<9}{b['steps']:>6}{b['gs_iterations_median']:>7.0f}"
              + "".join(f"{b['ms_per_step'][k]:13.2f}" for k in ("free_motion",) + STAGES + ("total",)))
    if problems:
        curves = gauss_seidel_curves(problems)
        out["gauss_seidel"] = curves
        plot_gauss_seidel(curves)
        for name, *_ in GS_VARIANTS:
            c = curves[name]
            print(f"Gauss-Seidel {name}: sweeps to 1e-6 median {c['sweeps_to_1e-6']['median']:.0f} (max "
                  f"{c['sweeps_to_1e-6']['max']}); residual after {CAPS[-4]} sweeps {c['residual'][-4]:.1e} in "
                  f"{c['ms'][-4]:.2f} ms")

    if not args.quick:
        floor = {c: run_floor(c, args.steps) for c in ("warped", "exact")}
        with factorization("lu"):
            floor["exact_lu"] = run_floor("exact", args.steps)
        out["liver_floor"] = floor
        _table("liver_floor", floor)
        ratio = floor["exact"]["ms_per_step"]["contact"] / floor["warped"]["ms_per_step"]["contact"]
        ratio_lu = floor["exact_lu"]["ms_per_step"]["contact"] / floor["warped"]["ms_per_step"]["contact"]
        out["liver_floor"]["exact_over_warped_contact"] = ratio
        out["liver_floor"]["exact_lu_over_warped_contact"] = ratio_lu
        print(f"contact stage: exact / warped = {ratio:.1f}x (by LU {ratio_lu:.1f}x); total ms/step exact "
              f"{floor['exact']['ms_per_step']['total']:.2f}, by LU {floor['exact_lu']['ms_per_step']['total']:.2f} "
              f"(SOFA: warped {SOFA_FLOOR_MS['warped']} ms/step in total, exact {SOFA_FLOOR_MS['exact']})")
    for run in (*press_results.values(), wide, dense, *(out.get("liver_floor", {}).values())):
        if isinstance(run, dict):
            run.pop("per_step", None)
    write_results(args.out or ("contact-quick" if args.quick else "contact"), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
