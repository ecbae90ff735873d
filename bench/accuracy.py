"""Error against run time: every accuracy knob against a reference, with the time it costs.

    python -m bench.accuracy [--quick] [--scheduler tcp://host:port] [--workers 2]

Sections (each cell an independent Dask task; plots in figures/accuracy_*.png, numbers in
bench/results/accuracy.json):
  solver     SOFA's beam scene, coarser (4.6 × 1 × 1 m, 30 × 6 × 6 cubes, E 3000 Pa, ν 0.3,
             density 1, dt 0.02 s, Rayleigh 0.1/0.1, "large"): CG iterations 5 … 400 with and
             without the Jacobi preconditioner, and CG tolerance 1e-1 … 1e-6. Error of each step
             against the direct solve of the same step from the same state
             (tissue.solver.reference.reference_step, scipy spsolve), and of the position after
             25 steps against the direct-solve trajectory; time per step of the Taichi solver.
  rotation   "large" and "polar" × float64 and float32 (each float32 cell re-initialises its own
             worker's backend), CG 25 and converged, against the direct trajectory with "polar".
  timestep   implicit Euler's numerical damping: the beam (E 3e4, no Rayleigh damping) released
             under gravity, dt 1 ms … 0.16 s against dt = 0.5 ms, converged CG.
  energy     static self-weight of a slender cantilever (1 × 0.05 × 0.05 m, 60 × 3 × 3 cubes,
             E 1e6 Pa, ν 0.3) under growing load: relative strain-energy error of co-rotational
             ("large", "polar") and linear against St Venant–Kirchhoff on the same mesh (Marchal
             et al. 2008: "under 2% with large rotations").
  elastica   the same cantilever against exact elastica values (tip load PL²/EI = 1, 2, 5, 10;
             self-weight qL³/EI = 1, 5, 10), refined 2, 3, 4, 6 cubes across (L/h = 20) with
             "large" (the default), 2, 3 with "polar" and St Venant–Kirchhoff (slower references),
             and the Richardson limit of the three finest "large" meshes.
  contact    the free block of bench/stability.py (4 × 4 × 2 cm, E 1e4 Pa, ν 0.45, dt 0.04 s,
             Rayleigh 0.1/0.1, converged Jacobi CG), μ 0.5, 25 steps: launched along the floor at
             0.3 m/s (slides, then sticks), and released on the 25° slope (sticks: tan 25° < μ).
             Compliance warped or exact × Gauss-Seidel sweeps 5 … 1000 (tolerance 1e-12 m) and
             tolerance 1e-2 … 1e-8 m (≤ 10,000 sweeps), against the exact compliance converged to
             1e-12 m (≤ 20,000 sweeps): error of the contact forces gathered on the nodes (over all
             steps) and of the positions after 25 steps, and the time per step (free motion +
             contact).

Which code computes what: static equilibria are Newton solves in bench/nonlinear_reference.py
(numpy/scipy; co-rotational forces as tissue.solver.reference, with their exact differenced
tangent); the simulator itself (tissue.solver.ImplicitEuler, Taichi) computes the dynamic cells
and, for the self-weight elastica cases, the same equilibria by dynamic relaxation (implicit Euler
with dt = 1 s and Rayleigh mass damping 2/s until no node moves 1e-10 m in a step, load ramped
through 1, 5, 10). The tip-load cases go through scipy only: the solver has no per-node external
force yet.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from .cluster import add_arguments, client, record, run_cells, worker_backend

# ---- scenes ----------------------------------------------------------------------------------

SOLVER_SCENE = dict(length=4.6, width=1.0, cells=(30, 6), young=3000.0, poisson=0.3, density=1.0,
                    dt=0.02, rayleigh=(0.1, 0.1), steps=25, compared=5)
TIMESTEP_SCENE = dict(length=4.6, width=1.0, cells=(18, 4), young=3e4, poisson=0.3, density=1.0,
                      duration=3.0, reference_dt=5e-4)
SLENDER = dict(length=1.0, width=0.05, young=1e6, poisson=0.3, density=1000.0)
TIP_LOADS = {1: 0.30172, 2: 0.49346, 5: 0.71379, 10: 0.81061}       # PL²/EI -> v/L (elastica)
SELF_WEIGHT = {1: 0.12347, 5: 0.49591, 10: 0.70020}                # qL³/EI -> v/L
ENERGY_LOADS = (0.1, 0.3, 1, 2, 3, 5, 10)                          # qL³/EI, growing rotation
GRAVITY = (0.0, 0.0, -9.81)
CONTACT_SCENES = ("floor", "slope")       # modes of bench.stability's friction cells
CONTACT = dict(friction=0.5, dt=0.04, steps=25)


def _beam(scene):
    from tissue.fem import Material
    from tissue.mesh import beam

    mesh = beam(scene["length"], scene["width"], scene["width"], scene["cells"][0], scene["cells"][1])
    fixed = np.flatnonzero(mesh.points[:, 0] <= 1e-9)
    return mesh, Material(scene["young"], scene["poisson"], scene["density"]), fixed


def _tip(mesh, x):
    tip = mesh.points[:, 0] >= mesh.points[:, 0].max() - 1e-9
    return float((x[tip] - mesh.points[tip])[:, 2].mean())


def _solver(mesh, material, fixed, dt, rotation="large", rayleigh=(0.1, 0.1), gravity=GRAVITY, **cg):
    from tissue.fem import CorotationalFEM
    from tissue.solver import CGSettings, ImplicitEuler

    fem = CorotationalFEM(mesh, material, rotation=rotation)
    return ImplicitEuler(fem, dt, gravity=gravity, rayleigh_mass=rayleigh[0], rayleigh_stiffness=rayleigh[1],
                         cg=CGSettings(**cg), fixed=fixed)


def _ms_per_step(stats, skip=1):
    per_step = np.sum([t for t in stats.times.values()], axis=0)
    return 1e3 * float(np.median(per_step[skip:]))


# ---- cells -----------------------------------------------------------------------------------

def direct_trajectory(cell: dict) -> dict:
    """The solver scene stepped by the direct solve (scipy): the reference trajectory."""
    from tissue.solver.reference import reference_step

    s = SOLVER_SCENE
    mesh, material, fixed = _beam(s)
    x, v = mesh.points.copy(), np.zeros_like(mesh.points)
    times, tips = [], []
    for _ in range(s["steps"]):
        start = time.perf_counter()
        x, v = reference_step(mesh, material, x, v, s["dt"], fixed=fixed, gravity=GRAVITY,
                              rayleigh_mass=s["rayleigh"][0], rayleigh_stiffness=s["rayleigh"][1],
                              rotation=cell["rotation"])
        times.append(time.perf_counter() - start)
        tips.append(_tip(mesh, x))
    return {**cell, "ms_per_step": 1e3 * float(np.median(times)), "tip": tips, "positions": x.tolist()}


def solver_cell(cell: dict) -> dict:
    """The solver scene with the Taichi solver; the first `compared` steps are each checked
    against the direct solve of the same step from the same state."""
    from tissue.solver.reference import reference_step

    worker_backend(cell["arch"], cell.get("precision", "f64"))
    s = SOLVER_SCENE
    mesh, material, fixed = _beam(s)
    cg = dict(max_iterations=cell["iterations"], tolerance=cell.get("tolerance", 1e-9),
              preconditioner=cell.get("preconditioner", "none"))
    solver = _solver(mesh, material, fixed, s["dt"], cell.get("rotation", "large"), s["rayleigh"], **cg)
    step_errors, tips = [], []
    for k in range(s["steps"]):
        if k < s["compared"]:
            x, v = solver.positions(), solver.velocities()
            x_ref, _ = reference_step(mesh, material, x, v, s["dt"], fixed=fixed, gravity=GRAVITY,
                                      rayleigh_mass=s["rayleigh"][0], rayleigh_stiffness=s["rayleigh"][1],
                                      rotation=cell.get("rotation", "large"))
        solver.step()
        x_new = solver.positions()
        if k < s["compared"]:
            step_errors.append(float(np.linalg.norm(x_new - x_ref) / np.linalg.norm(x_ref - x)))
        tips.append(_tip(mesh, x_new))
    return {**cell, "ms_per_step": _ms_per_step(solver.stats), "step_error": float(np.mean(step_errors)),
            "cg_iterations": float(np.mean(solver.stats.history["cg_iterations"])), "tip": tips,
            "positions": solver.positions().tolist()}


def timestep_cell(cell: dict) -> dict:
    """The undamped beam released under gravity with time step cell["dt"]: tip history."""
    worker_backend(cell["arch"])
    s = TIMESTEP_SCENE
    mesh, material, fixed = _beam(s)
    solver = _solver(mesh, material, fixed, cell["dt"], rayleigh=(0.0, 0.0), max_iterations=2000,
                     tolerance=1e-10, preconditioner="jacobi")
    steps = round(s["duration"] / cell["dt"])
    tips = [0.0]
    for _ in range(steps):
        solver.step()
        tips.append(_tip(mesh, solver.positions()))
    return {**cell, "ms_per_step": _ms_per_step(solver.stats), "tip": tips}


def _slender(n):
    from bench.nonlinear_reference import Body, clamped_nodes
    from tissue.fem import Material
    from tissue.mesh import beam

    s = SLENDER
    mesh = beam(s["length"], s["width"], s["width"], 20 * n, n)
    return Body(mesh, Material(s["young"], s["poisson"], s["density"]), clamped_nodes(mesh))


def _loads(body, kind, k):
    """External nodal forces of load level k (PL²/EI or qL³/EI) on the slender cantilever."""
    from bench.nonlinear_reference import body_load, tip_load

    s = SLENDER
    EI = s["young"] * s["width"] ** 4 / 12
    if kind == "tip":
        return tip_load(body.mesh, (0.0, 0.0, -k * EI / s["length"] ** 2))
    return body_load(body, (0.0, 0.0, -_gravity(k)))


def _gravity(k):
    s = SLENDER
    return k * s["young"] * s["width"] ** 2 / (12 * s["density"] * s["length"] ** 3)


def static_cell(cell: dict) -> dict:
    """Equilibria of one model along a chain of loads (each warm-started from the last)."""
    from bench.nonlinear_reference import solve_static, strain_energy, tip_deflection

    body = _slender(cell["n"])
    mesh, L = body.mesh, SLENDER["length"]
    x, previous, rows = None, 0.0, []
    start = time.perf_counter()
    for k in cell["loads"]:
        result = solve_static(body, cell["model"], _loads(body, cell["kind"], k), x0=x, start=previous / k,
                              increments=2)
        x, previous = result.x, k
        near = np.isclose(mesh.points[:, 0], L - L / (20 * cell["n"]))
        tip = np.isclose(mesh.points[:, 0], L)
        d = x[tip].mean(0) - x[near].mean(0)
        rows.append(dict(load=k, deflection=tip_deflection(mesh, x)[0] / L, energy=strain_energy(body, cell["model"], x),
                         tip_angle=math.degrees(math.atan2(-d[2], d[0])), newton=result.newton_iterations,
                         residual=result.residual))
    return {**cell, "rows": rows, "seconds": time.perf_counter() - start}


def relaxation_cell(cell: dict) -> dict:
    """The self-weight equilibria computed by the simulator: dynamic relaxation (see docstring)."""
    from bench.nonlinear_reference import tip_deflection

    worker_backend(cell["arch"])
    body = _slender(cell["n"])
    mesh = body.mesh
    x, rows = mesh.points.copy(), []
    start = time.perf_counter()
    for k in cell["loads"]:
        solver = _solver(mesh, body.material, body.fixed, 1.0, cell.get("rotation", "large"), rayleigh=(2.0, 0.0),
                         gravity=(0.0, 0.0, -_gravity(k)), max_iterations=20000, tolerance=1e-10,
                         preconditioner="jacobi")
        solver.set_state(x, np.zeros_like(x))
        for steps in range(1, 301):
            solver.step()
            if np.abs(solver.velocities()).max() * solver.dt < 1e-10 * SLENDER["length"]:
                break
        x = solver.positions()
        rows.append(dict(load=k, deflection=tip_deflection(mesh, x)[0] / SLENDER["length"], steps=steps,
                         cg_iterations=float(np.mean(solver.stats.history["cg_iterations"]))))
    return {**cell, "rows": rows, "seconds": time.perf_counter() - start}


def contact_cell(cell: dict) -> dict:
    """A friction cell of bench/stability.py (its block, initial state and obstacle) with converged
    CG and the cell's compliance and Gauss-Seidel stopping rule: contact forces gathered on the
    nodes at every step, final positions, ms per step."""
    from bench import stability
    from tissue.contact.pipeline import Contact, ContactStage
    from tissue.fem import Material

    worker_backend(cell["arch"])
    scene = dict(case="friction", mode=cell["scene"], friction=CONTACT["friction"], dt=CONTACT["dt"])
    mesh = stability._mesh(stability.body_of(scene))
    x, v, fixed = stability.initial_state(scene, mesh)
    solver = _solver(mesh, Material(stability.TISSUE["young"], stability.TISSUE["poisson"], 1000.0), fixed,
                     CONTACT["dt"], max_iterations=500, tolerance=1e-10, preconditioner="jacobi")
    solver.set_state(x, v)
    stage = ContactStage([solver], stability.obstacles(scene, mesh), Contact(
        friction=CONTACT["friction"], distance=stability.CONTACT_DISTANCE, compliance=cell["compliance"],
        tolerance=cell["tolerance"], max_iterations=cell["iterations"]), stats=solver.stats)
    forces = []
    for _ in range(CONTACT["steps"]):
        solver.step()
        r = stage.step()
        f = np.zeros_like(x)
        np.add.at(f, r.contacts.vertex, r.contact_forces)
        forces.append(f)
    history = solver.stats.history
    return {**cell, "ms_per_step": _ms_per_step(solver.stats), "forces": np.asarray(forces).tolist(),
            "positions": solver.positions().tolist(), "start": x.tolist(),
            "gs_iterations": float(np.mean(history["gs_iterations"])), "gs_residual": float(max(history["gs_residual"])),
            "rows": int(max(history["rows"]))}


def run_cell(cell: dict) -> dict:
    return {"direct": direct_trajectory, "solver": solver_cell, "timestep": timestep_cell,
            "static": static_cell, "relaxation": relaxation_cell, "contact": contact_cell}[cell["section"]](cell)


# ---- the sweep -------------------------------------------------------------------------------

def cells(quick: bool, arch: str) -> list[dict]:
    from tissue.solver.parameters import PRECONDITIONERS

    out = [dict(section="direct", rotation=r) for r in ("large", "polar")]
    for pre in PRECONDITIONERS:
        for it in ((5, 25, 100, 400) if quick else (5, 10, 25, 50, 100, 200, 400)):
            out.append(dict(section="solver", group="iterations", preconditioner=pre, iterations=it))
    for tol in ((1e-2, 1e-4) if quick else (1e-1, 1e-2, 1e-3, 1e-4, 1e-6)):
        out.append(dict(section="solver", group="tolerance", preconditioner="jacobi", iterations=1000, tolerance=tol))
    for rot in ("large", "polar"):
        for precision in ("f64", "f32"):
            for it, tol, pre in ((25, 1e-9, "none"), (1000, 1e-5, "jacobi")):
                out.append(dict(section="solver", group="rotation", rotation=rot, precision=precision,
                                iterations=it, tolerance=tol, preconditioner=pre))
    for dt in (TIMESTEP_SCENE["reference_dt"], 1e-3, 2e-3, 5e-3, 0.01, 0.02, 0.04, 0.08, 0.16):
        out.append(dict(section="timestep", dt=dt))
    for model in ("stvk", "large", "polar", "linear"):
        out.append(dict(section="static", group="energy", model=model, kind="self", n=3, loads=list(ENERGY_LOADS)))
    for n in ((2, 3, 4) if quick else (2, 3, 4, 6)):
        for kind, loads in (("tip", list(TIP_LOADS)), ("self", list(SELF_WEIGHT))):
            for model in ("large", "polar", "stvk", "linear"):
                if model in ("polar", "stvk") and n > 3:
                    continue   # the slowest references; "large" (the default) carries the fine meshes
                out.append(dict(section="static", group="elastica", model=model, kind=kind, n=n, loads=loads))
        if n <= (3 if quick else 4):
            out.append(dict(section="relaxation", n=n, loads=list(SELF_WEIGHT)))
    for scene in CONTACT_SCENES:
        out.append(dict(section="contact", scene=scene, group="reference", compliance="exact", iterations=20000,
                        tolerance=1e-12))
        for compliance in ("warped", "exact"):
            for it in ((5, 25, 100, 1000) if quick else (5, 10, 25, 50, 100, 200, 1000)):
                out.append(dict(section="contact", scene=scene, group="iterations", compliance=compliance,
                                iterations=it, tolerance=1e-12))
            for tol in ((1e-3, 1e-6) if quick else (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8)):
                out.append(dict(section="contact", scene=scene, group="tolerance", compliance=compliance,
                                iterations=10000, tolerance=tol))
    for c in out:
        c["arch"] = arch
    # Longest first, so that the two workers finish together.
    return sorted(out, key=lambda c: -(c.get("n", 0) ** 3 * (2 if c.get("model") == "polar" else 1)))


def richardson(h, v):
    """v(h) = v∞ + C h^p through three (h, v): (v∞, p), or None if the three are not monotone."""
    from scipy.optimize import brentq

    (h1, h2, h3), (v1, v2, v3) = h, v
    ratio = (v2 - v1) / (v3 - v2)
    if not ratio > 0:
        return None
    f = lambda p: (h1 ** p - h2 ** p) / (h2 ** p - h3 ** p) - ratio
    try:
        p = brentq(f, 0.2, 6.0)
    except ValueError:
        return None
    return v3 + (v3 - v2) * h3 ** p / (h2 ** p - h3 ** p), p


def analyse(results: list[dict]) -> dict:
    by = lambda **kw: [r for r in results if all(r.get(k) == v for k, v in kw.items()) and "error" not in r]
    out = {}
    # solver and rotation/precision: errors against the direct trajectories
    direct = {r["rotation"]: r for r in by(section="direct")}
    x0 = _beam(SOLVER_SCENE)[0].points
    error = lambda r, ref: float(np.linalg.norm(np.asarray(r["positions"]) - ref) / np.linalg.norm(ref - x0))
    if "positions" in direct["polar"]:   # (absent when re-plotting from the JSON)
        direct["large"]["gap_to_polar"] = error(direct["large"], np.asarray(direct["polar"]["positions"]))
        for r in by(section="solver"):
            r["trajectory_error"] = error(r, np.asarray(direct["polar" if r["group"] == "rotation" else "large"]["positions"]))
            r["tip_after_7"] = r["tip"][6]
    out["direct"] = {k: dict(ms_per_step=v["ms_per_step"], tip_after_7=v["tip"][6], tip_final=v["tip"][-1],
                             gap_to_polar=v.get("gap_to_polar", 0.0)) for k, v in direct.items()}
    out["solver"] = [{k: r[k] for k in ("group", "preconditioner", "iterations", "tolerance", "rotation", "precision",
                                        "ms_per_step", "cg_iterations", "step_error", "trajectory_error", "tip_after_7")
                      if k in r} for r in by(section="solver")]
    # time step: tip history against the small-step reference, numerical damping
    steps = sorted(by(section="timestep"), key=lambda r: r["dt"])
    ref = steps[0]
    t_ref = np.arange(len(ref["tip"])) * ref["dt"]
    amplitude = np.sqrt(np.mean((np.asarray(ref["tip"]) - np.mean(ref["tip"])) ** 2))
    turning = _extrema(np.asarray(ref["tip"]))[0]
    omega = math.pi / (np.mean(np.diff(turning)) * ref["dt"])   # turning points are half a period apart
    out["omega"] = omega
    out["timestep"] = []
    base = _damping(t_ref, np.asarray(ref["tip"])) - _implicit_euler_damping(omega, ref["dt"])
    for r in steps:
        t = np.arange(len(r["tip"])) * r["dt"]
        err = np.sqrt(np.mean((np.asarray(r["tip"]) - np.interp(t, t_ref, ref["tip"])) ** 2)) / amplitude
        out["timestep"].append(dict(dt=r["dt"], ms_per_step=r["ms_per_step"], ms_per_second=r["ms_per_step"] / r["dt"],
                                    error=float(err), damping=_damping(t, np.asarray(r["tip"])) - base,
                                    damping_theory=_implicit_euler_damping(omega, r["dt"])))
    # energy under growing rotation
    energy = {r["model"]: r["rows"] for r in by(section="static", group="energy")}
    if "stvk" in energy:
        out["energy"] = []
        for i, row in enumerate(energy["stvk"]):
            entry = dict(load=row["load"], tip_angle=row["tip_angle"], stvk_energy=row["energy"])
            for m in ("large", "polar", "linear"):
                if m in energy:
                    entry[f"{m}_energy_error"] = abs(energy[m][i]["energy"] - row["energy"]) / row["energy"]
                    entry[f"{m}_deflection_error"] = abs(energy[m][i]["deflection"] - row["deflection"]) / row["deflection"]
            out["energy"].append(entry)
    # elastica: error per mesh, Richardson limit of the three finest "large" meshes
    out["elastica"] = []
    for kind, exact in (("tip", TIP_LOADS), ("self", SELF_WEIGHT)):
        for model in ("large", "polar", "stvk", "linear"):
            series = sorted(by(section="static", group="elastica", kind=kind, model=model), key=lambda r: r["n"])
            for r in series:
                for row in r["rows"]:
                    out["elastica"].append(dict(kind=kind, model=model, n=r["n"], load=row["load"],
                                                deflection=row["deflection"], exact=exact[row["load"]],
                                                error=row["deflection"] / exact[row["load"]] - 1))
        for r in by(section="relaxation"):
            if kind == "self":
                for row in r["rows"]:
                    out["elastica"].append(dict(kind=kind, model="simulator (large)", n=r["n"], load=row["load"],
                                                deflection=row["deflection"], exact=exact[row["load"]],
                                                error=row["deflection"] / exact[row["load"]] - 1, steps=row["steps"],
                                                cg_iterations=row["cg_iterations"]))
    # contact: forces and positions against the exact, tightly converged run of the same scene
    out["contact"] = []
    for scene in CONTACT_SCENES:
        ref = next((r for r in by(section="contact", scene=scene, group="reference") if "forces" in r), None)
        if ref is None:       # (re-plotting from the JSON: the errors are stored there)
            out["contact"] += [{k: r[k] for k in CONTACT_KEYS if k in r} for r in by(section="contact", scene=scene)]
            continue
        F, x, x0 = (np.asarray(ref[k]) for k in ("forces", "positions", "start"))
        for r in by(section="contact", scene=scene):
            r["force_error"] = float(np.linalg.norm(np.asarray(r["forces"]) - F) / np.linalg.norm(F))
            r["position_error"] = float(np.linalg.norm(np.asarray(r["positions"]) - x) / np.linalg.norm(x - x0))
            out["contact"].append({k: r[k] for k in CONTACT_KEYS})
    out["extrapolated"] = []
    for kind, exact in (("tip", TIP_LOADS), ("self", SELF_WEIGHT)):
        rows = [e for e in out["elastica"] if e["kind"] == kind and e["model"] == "large"]
        ns = sorted({e["n"] for e in rows})[-3:]
        if len(ns) == 3:
            for load, value in exact.items():
                v = [next(e["deflection"] for e in rows if e["n"] == n and e["load"] == load) for n in ns]
                fit = richardson([1 / n for n in ns], v)
                if fit:
                    out["extrapolated"].append(dict(kind=kind, load=load, meshes=ns, limit=fit[0], order=fit[1],
                                                    exact=value, error=fit[0] / value - 1))
    return out


CONTACT_KEYS = ("scene", "group", "compliance", "iterations", "tolerance", "ms_per_step", "gs_iterations",
                "gs_residual", "rows", "force_error", "position_error")


def _extrema(z):
    """Indices of the turning points of z about its final third's mean, and their amplitudes."""
    dz = z - np.mean(z[2 * len(z) // 3:])
    idx = [i for i in range(1, len(z) - 1) if (dz[i] - dz[i - 1]) * (dz[i + 1] - dz[i]) < 0]
    return np.asarray(idx, dtype=int), np.abs(dz[idx])


def _damping(t, z):
    """Damping ratio from the decay of the half-cycle amplitudes (log-linear fit), or nan."""
    idx, a = _extrema(z)
    if len(idx) < 3:
        return math.nan
    delta = -2 * np.polyfit(np.arange(len(a)), np.log(a), 1)[0]   # log decrement per cycle
    return float(delta / math.sqrt(4 * math.pi ** 2 + delta ** 2))


def _implicit_euler_damping(omega, h):
    """ζ of implicit Euler on an undamped oscillator: the step's eigenvalue 1 / (1 - iωh)."""
    decay, phase = 0.5 * math.log1p((omega * h) ** 2), math.atan(omega * h)
    return decay / math.hypot(decay, phase)


# ---- plots -----------------------------------------------------------------------------------

def plot(summary: dict, results: list[dict]) -> list:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from .common import FIGURES

    FIGURES.mkdir(exist_ok=True)
    paths = []
    # 1. solver knobs
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    solver = summary["solver"]
    for ax, key, title in ((axes[0], "step_error", "one step vs the direct solve of that step"),
                           (axes[1], "trajectory_error", "after 25 steps vs the direct trajectory")):
        for pre, style in zip(sorted({r["preconditioner"] for r in solver if r["group"] == "iterations"}),
                              ("o-", "s-", "D-", "v-", "p-")):
            rows = sorted([r for r in solver if r["group"] == "iterations" and r["preconditioner"] == pre],
                          key=lambda r: r["iterations"])
            ax.plot([r["ms_per_step"] for r in rows], [r[key] for r in rows], style, label=f"CG iterations, {pre}")
            for r in rows:
                ax.annotate(str(r["iterations"]), (r["ms_per_step"], r[key]), textcoords="offset points",
                            xytext=(4, 4), fontsize=8)
        rows = sorted([r for r in solver if r["group"] == "tolerance"], key=lambda r: -r["tolerance"])
        ax.plot([r["ms_per_step"] for r in rows], [r[key] for r in rows], "^--", label="tolerance, jacobi (≤1000)")
        for r in rows:
            ax.annotate(f"{r['tolerance']:g}", (r["ms_per_step"], r[key]), textcoords="offset points",
                        xytext=(4, -10), fontsize=8)
        if key == "trajectory_error":
            d = summary["direct"]["large"]
            ax.axvline(d["ms_per_step"], color="k", ls=":", label=f"direct solve (scipy), {d['ms_per_step']:.0f} ms")
        ax.set(xscale="log", yscale="log", xlabel="ms per step (Taichi, 1 CPU thread)", ylabel="relative error",
               title=title)
        _plain_log_ticks(ax)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    ax = axes[2]
    for rotation, color in (("large", "C0"), ("polar", "C3")):
        for precision, marker in (("f64", "o"), ("f32", "x")):
            rows = sorted((r for r in solver if r["group"] == "rotation" and r["rotation"] == rotation
                           and r["precision"] == precision), key=lambda r: r["iterations"])
            ax.plot([r["ms_per_step"] for r in rows], [r["trajectory_error"] for r in rows], marker + "-",
                    color=color, ms=9, label=f"{rotation} {precision}: CG 25 → tol 1e-5 Jacobi")
    d = summary["direct"]
    ax.plot(d["large"]["ms_per_step"], d["large"]["gap_to_polar"], "k*", ms=12, label="direct solve, large (scipy)")
    _plain_log_ticks(ax)
    ax.legend(fontsize=8)
    ax.set(xscale="log", yscale="log", xlabel="ms per step", ylabel="relative error after 25 steps",
           title="rotation × precision, vs the direct trajectory with polar")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    paths.append(FIGURES / "accuracy_solver.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # 2. time step
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    steps = sorted([r for r in results if r.get("section") == "timestep" and "tip" in r], key=lambda r: r["dt"])
    for r in steps:
        if r["dt"] in (TIMESTEP_SCENE["reference_dt"], 0.01, 0.04, 0.16):
            t = np.arange(len(r["tip"])) * r["dt"]
            axes[0].plot(t, r["tip"], label=f"dt = {r['dt']:g} s", lw=1.2)
    axes[0].set(xlabel="time (s)", ylabel="tip deflection (m)", title="undamped beam released under gravity")
    axes[0].legend(fontsize=8)
    rows = [r for r in summary["timestep"] if r["dt"] > TIMESTEP_SCENE["reference_dt"]]
    axes[1].plot([r["ms_per_second"] for r in rows], [r["error"] for r in rows], "o-")
    for r in rows:
        axes[1].annotate(f"{r['dt']:g} s, ζ={r['damping']:.3f}", (r["ms_per_second"], r["error"]),
                         textcoords="offset points", xytext=(5, 3), fontsize=8)
    axes[1].set(xscale="log", yscale="log", xlabel="ms of computation per simulated second",
                ylabel="RMS tip error / RMS amplitude", title="vs dt = 0.5 ms")
    axes[1].grid(True, which="both", alpha=0.3)
    rows = summary["timestep"]
    wh = np.geomspace(min(r["dt"] for r in rows), max(r["dt"] for r in rows), 100) * summary["omega"]
    axes[2].plot(wh, [_implicit_euler_damping(1.0, w) for w in wh], "k-", label="implicit Euler, 1 / (1 − iωh)")
    rows = rows[1:]   # the reference itself matches by construction
    axes[2].plot([summary["omega"] * r["dt"] for r in rows], [r["damping"] for r in rows], "o",
                 label="measured: tip decay, less the reference's non-numerical part")
    axes[2].set(xscale="log", yscale="log", xlabel=f"ωh (ω = {summary['omega']:.2f} rad/s, first mode)",
                ylabel="damping ratio ζ", title="numerical damping")
    axes[2].legend(fontsize=8)
    axes[2].grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    paths.append(FIGURES / "accuracy_timestep.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # 3. energy under growing rotation, and the elastica
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    energy = summary.get("energy", [])
    for m, c in (("large", "C0"), ("polar", "C3"), ("linear", "C7")):
        if energy and f"{m}_energy_error" in energy[0]:
            axes[0].plot([e["tip_angle"] for e in energy], [100 * e[f"{m}_energy_error"] for e in energy], "o-",
                         color=c, label=m)
    axes[0].axhline(2.0, color="k", ls=":", label="2 % (Marchal et al. 2008)")
    axes[0].set(yscale="log", xlabel="tip rotation (°)", ylabel="strain-energy error vs St Venant–Kirchhoff (%)",
                title="self-weight, same mesh (3 cubes across)")
    axes[0].grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    el = summary["elastica"]
    ax = axes[1]
    for kind, exact, marker in (("tip", TIP_LOADS, "o"), ("self", SELF_WEIGHT, "s")):
        ax.plot(list(exact), list(exact.values()), marker, color="k", ms=8, mfc="none",
                label=f"elastica, {'tip load PL²/EI' if kind == 'tip' else 'self-weight qL³/EI'}")
        ns = sorted({e["n"] for e in el if e["kind"] == kind and e["model"] == "large"})
        for i, n in enumerate(ns):
            rows = [e for e in el if e["kind"] == kind and e["model"] == "large" and e["n"] == n]
            ax.plot([e["load"] for e in rows], [e["deflection"] for e in rows], marker + "-",
                    color=plt.cm.viridis(i / max(1, len(ns) - 1)), ms=4, lw=1,
                    label=f"large, {n} cubes across" if kind == "tip" else None)
        rows = [e for e in el if e["kind"] == kind and e["model"] == "linear" and e["n"] == ns[-1]]
        ax.plot([e["load"] for e in rows], [e["deflection"] for e in rows], marker + ":", color="C7",
                label="linear (finest)" if kind == "tip" else None)
    ax.set(xlabel="load", ylabel="tip deflection v / L", ylim=(0, 1.2), title="cantilever vs exact elastica")
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    ax = axes[2]
    for kind, exact, ls in (("tip", TIP_LOADS, "-"), ("self", SELF_WEIGHT, "--")):
        for j, load in enumerate(exact):
            for model, marker in (("large", "o"), ("polar", "x"), ("simulator (large)", "+")):
                rows = sorted([e for e in el if e["kind"] == kind and e["model"] == model and e["load"] == load],
                              key=lambda e: e["n"])
                if rows:
                    ax.plot([e["n"] for e in rows], [100 * abs(e["error"]) for e in rows], marker + ls,
                            color=f"C{j + (4 if kind == 'self' else 0)}", ms=6,
                            label=f"{'P' if kind == 'tip' else 'q'} = {load}" if model == "large" else None)
    ax.set(xscale="log", yscale="log", xlabel="cubes across the section (L/h = 20)", ylabel="|v/L error| (%)",
           title="convergence: o large, x polar, + simulator (dyn. relaxation)")
    ns = sorted({e["n"] for e in el})
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    paths.append(FIGURES / "accuracy_rotation_elastica.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # 4. contact: compliance model and Gauss-Seidel stopping rule
    contact = summary.get("contact", [])
    if contact:
        fig, axes = plt.subplots(2, 2, figsize=(12, 9))
        for col, scene in enumerate(CONTACT_SCENES):
            rows = [r for r in contact if r["scene"] == scene]
            for row, key in enumerate(("force_error", "position_error")):
                ax = axes[row, col]
                for compliance, color in (("warped", "C0"), ("exact", "C3")):
                    for group, style, label in (("iterations", "o-", "GS sweeps"), ("tolerance", "^--", "GS tolerance (m)")):
                        line = sorted((r for r in rows if r["compliance"] == compliance and r["group"] == group),
                                      key=lambda r: r["iterations"] if group == "iterations" else -r["tolerance"])
                        # An error of 0 (the reference itself) has no place on a log axis.
                        ys = [max(r[key], 1e-16) for r in line]
                        ax.plot([r["ms_per_step"] for r in line], ys, style, color=color, label=f"{compliance}, {label}")
                        for r, y in zip(line, ys):
                            ax.annotate(str(r["iterations"]) if group == "iterations" else f"{r['tolerance']:g}",
                                        (r["ms_per_step"], y), textcoords="offset points",
                                        xytext=(4, 4 if group == "iterations" else -10), fontsize=7)
                ax.set(xscale="log", yscale="log", xlabel="ms per step (free motion + contact, 1 CPU thread)",
                       ylabel=f"relative {'contact-force' if key == 'force_error' else 'position'} error",
                       title=f"{scene}: {'nodal contact forces, all 25 steps' if key == 'force_error' else 'positions after 25 steps'}"
                             " vs exact, 1e-12 m")
                ax.grid(True, which="both", alpha=0.3)
                ax.legend(fontsize=7)
        fig.tight_layout()
        paths.append(FIGURES / "accuracy_contact.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    return paths


def _plain_log_ticks(ax):
    from matplotlib.ticker import LogLocator, NullFormatter

    ax.xaxis.set_major_locator(LogLocator(base=10))
    ax.xaxis.set_minor_formatter(NullFormatter())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_arguments(parser)
    parser.add_argument("--quick", action="store_true", help="fewer knob values, meshes up to 4 cubes across")
    parser.add_argument("--replot", action="store_true", help="redraw the figures from bench/results/accuracy.json")
    args = parser.parse_args(argv)
    from bench import accuracy   # by module name: the workers import it
    from .common import RESULTS, write_results

    if args.replot:
        data = json.loads((RESULTS / "accuracy.json").read_text())
        summary = analyse(data["cells"])
        for p in plot(summary, data["cells"]):
            print(f"# wrote {p}")
        (RESULTS / "accuracy.md").write_text(report(summary) + "\n")
        print(report(summary))
        return

    with client(args) as c:
        info = record(c, args)
        results = run_cells(c, accuracy.run_cell, cells(args.quick, args.arch), "accuracy")
    for r in results:
        if "error" in r:
            print("cell failed:", {k: v for k, v in r.items() if k not in ("positions", "tip")})
    summary = analyse(results)

    slim = [{k: v for k, v in r.items() if k not in ("positions", "forces", "start")} for r in results]
    write_results("accuracy", {"machine": info, "summary": summary, "cells": slim})
    for p in plot(summary, results):
        print(f"# wrote {p}")
    (RESULTS / "accuracy.md").write_text(report(summary) + "\n")
    print(report(summary))


def report(summary: dict) -> str:
    """The markdown tables of bench/README-accuracy.md."""
    lines = ["| knob | ms/step | CG its | step error | error after 25 steps | tip after 7 steps (m) |",
             "|---|---|---|---|---|---|"]
    for r in summary["solver"]:
        knob = (f"{r['iterations']} its, {r['preconditioner']}" if r["group"] == "iterations" else
                f"tol {r['tolerance']:g}, jacobi" if r["group"] == "tolerance" else
                f"{r['rotation']} {r['precision']} {'CG 25' if r['iterations'] == 25 else 'tol 1e-5 jacobi'}")
        lines.append(f"| {knob} | {r['ms_per_step']:.2f} | {r['cg_iterations']:.0f} | {r['step_error']:.2e} | "
                     f"{r['trajectory_error']:.2e} | {r['tip_after_7']:.4f} |")
    for k, d in summary["direct"].items():
        lines.append(f"| direct solve, {k} (scipy) | {d['ms_per_step']:.1f} | – | 0 | – | {d['tip_after_7']:.4f} |")
    lines += ["", f"| dt (s) | ωh | ms/step | ms per simulated s | RMS tip error | ζ measured | ζ of implicit Euler |",
              "|---|---|---|---|---|---|---|"]
    for r in summary["timestep"]:
        lines.append(f"| {r['dt']:g} | {summary['omega'] * r['dt']:.3f} | {r['ms_per_step']:.2f} | {r['ms_per_second']:.0f} "
                     f"| {r['error']:.3f} | {r['damping']:.4f} | {r['damping_theory']:.4f} |")
    if summary.get("energy"):
        lines += ["", "| qL³/EI | tip rotation | energy error large | polar | linear | deflection error large | linear |",
                  "|---|---|---|---|---|---|---|"]
        for e in summary["energy"]:
            lines.append(f"| {e['load']:g} | {e['tip_angle']:.1f}° | {100 * e['large_energy_error']:.2f} % | "
                         f"{100 * e['polar_energy_error']:.2f} % | {100 * e['linear_energy_error']:.1f} % | "
                         f"{100 * e['large_deflection_error']:.2f} % | {100 * e['linear_deflection_error']:.1f} % |")
    if summary.get("contact"):
        lines += ["", "| scene | compliance | GS sweeps (cap) | tolerance (m) | ms/step | sweeps (mean) | residual (max, m) "
                  "| rows | force error | position error |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in summary["contact"]:
            lines.append(f"| {r['scene']} | {r['compliance']}{' (reference)' if r['group'] == 'reference' else ''} | "
                         f"{r['iterations']} | {r['tolerance']:g} | {r['ms_per_step']:.2f} | {r['gs_iterations']:.0f} | "
                         f"{r['gs_residual']:.1e} | {r['rows']} | {r['force_error']:.2e} | {r['position_error']:.2e} |")
    finest = lambda m: max((e["n"] for e in summary["elastica"] if e["model"] == m), default=0)
    large_ns = sorted({e["n"] for e in summary["elastica"] if e["model"] == "large"})
    lines += ["", "| load | exact v/L | " + " | ".join(f"large n={n}" for n in large_ns)
              + f" | polar n={finest('polar')} | simulator n={finest('simulator (large)')} | Richardson limit (large) |",
              "|---|---|" + "---|" * (len(large_ns) + 3)]
    for kind, exact in (("tip", TIP_LOADS), ("self", SELF_WEIGHT)):
        for load, value in exact.items():
            rows = [e for e in summary["elastica"] if e["kind"] == kind and e["load"] == load]
            cells = [f"{100 * e['error']:+.1f} %" for e in sorted((e for e in rows if e["model"] == "large"),
                                                                   key=lambda e: e["n"])]
            last = lambda m: (f"{100 * max((e for e in rows if e['model'] == m), key=lambda e: e['n'])['error']:+.1f} %"
                              if any(e["model"] == m for e in rows) else "–")
            ex = next((e for e in summary["extrapolated"] if e["kind"] == kind and e["load"] == load), None)
            lines.append(f"| {'PL²/EI' if kind == 'tip' else 'qL³/EI'} = {load} | {value} | " + " | ".join(cells)
                         + f" | {last('polar')} | {last('simulator (large)')} | "
                         + (f"{ex['limit']:.4f} ({100 * ex['error']:+.1f} %, order {ex['order']:.1f})" if ex else "–")
                         + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
