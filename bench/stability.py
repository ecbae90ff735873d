"""Stability on stiff and extreme cases: does every cell stay bounded, or get refused clearly?

    python -m bench.stability [--quick] [--scheduler tcp://host:port] [--workers 2]
    python -m bench.stability --refused --missing     # after a change of tissue.fem.regime

The scene: a small cantilever (0.1 × 0.02 × 0.02 m, 10 × 2 × 2 cubes, 240 tetrahedra, density
1000), clamped at x = 0, under gravity, Rayleigh 0.1 / 0.1, the solver a user gets from the
scenes (`CG`: multigrid-preconditioned CG to ‖r‖ ≤ 1e-3 ‖b‖, at most 100 iterations, warm-started; the energy
check `tissue.solver.step_control`, `STEP_CONTROL`, with the energy budget
`tissue.solver.energy_budget`, `ENERGY_BUDGET`, closed again after a contact correction; a cell's
"cg", "step_control" and "energy_budget" entries override them), each cell with both rotation methods ("large": edge frames, SOFA's default; "polar"), and the soft
end (E ≤ 1e3 Pa), the special cells and the floor's impacts, jerk and rest with "invertible" (tissue.fem:
"polar" plus a compression limit). Cells:
  material   E 1e2 … 1e8 Pa × ν 0 … 0.499 × dt 1e-3 … 0.5 s, from rest, for max(20, 1 s / dt)
             steps (at most 1,000). The self-weight strain ρ g L / E is 9.8 at 1e2 Pa, 0.98 at
             1e3 Pa, 0.098 at 1e4 Pa: the soft end is far outside small strain on purpose;
  twist      both ends clamped, the far end turned 180° about the axis: smoothly along the beam,
             or abruptly (only the end face turned);
  inverted   initial positions that invert elements: one node pushed out through the body, or the
             free half mirrored (z → −z: the same shape, every element inside out);
  impact     a large initial velocity: 10 m/s uniform, or a random field of 5 m/s per node;
  jerk       the clamped end displaced by half the length in one step;
the special cells with E = 1e4 Pa, ν = 0.45, dt = 0.04 s for 250 steps (10 s), and with contact
(tissue.contact: rigid obstacles, Coulomb friction by projected Gauss-Seidel, compliance warping,
the scene defaults: alarm distance 2 mm, tolerance 1e-6 m, 100 sweeps):
  friction   a free soft block (4 × 4 × 2 cm, 192 tetrahedra) on a rigid floor, launched along it
             at 0.3 m/s (it slides, then sticks where μ > 0), and released on a plane tilted by
             25° (tan 25° = 0.47: slides for μ ≤ 0.1, sticks for μ ≥ 0.5); μ = 0, 0.1, 0.5, 1, 10;
  press      a slab (10 × 10 × 2 cm, 18 × 18 × 2 cubes, 3,888 tetrahedra) on the floor, pressed
             flat by a rigid plate moving down 5 mm in 2 s then held, μ = 0.5 (100 steps): from
             the first step the floor's 361 bottom vertices and the plate's 361 top ones (found
             by the alarm distance at the step's start: a step's free motion drops the slab
             g dt² = 15.7 mm), and the side faces' 72 middle vertices, below the floor in the
             free motion: 2,382 rows; once the slab is pressed thinner than g dt² + the alarm
             distance, the top vertices are within it of the floor in the free motion too: 3,465
             rows (722 contacts pushing);
  impact and jerk with a floor under the cantilever (its bottom face resting on it), μ = 0.5; and
             the 10 m/s impact onto it again at dt 2 ms (the dt its refusal at 0.04 s names);
  rest       the clamped cantilever from rest on that floor, sagging onto it (μ = 0.5).
Each cell ends as (`classify`)
  bounded    finite at every step, and the total energy E (kinetic + elastic + gravity's
             potential) never above its start plus the work W done on the body by external and
             contact forces (the moving obstacles': static obstacles and fixed nodes do none) by
             more than ALLOWANCE (1 %) of the energy scale: max over steps of E − W − E₀ ≤ 0.01
             scale; and no element inverted at the end. The elastic energy is the model's own:
             the polar co-rotational energy for "large" and "polar" ("large" has no energy of its
             own: its forces are not a gradient), plus the compression limit's for "invertible";
  refused    a TissueError before the first step, with its message (bad input, or a configuration
             outside its element's or contact's regime: tissue.fem.regime);
  diverged   a TissueError during the run (e.g. "the simulation diverged ..."): a failure;
  inverted   bounded energy, but elements inverted at the end (a failure; whether the solver
             warned "N elements are inverted ..." is recorded with it);
  energy     finite but the energy rose past the allowance (a failure);
  silent-nan non-finite state without an error (must never happen).
Beside the outcome each cell reports how its implicit solves ended (`solve_measures`: the CG's
relative residual, the steps at the iteration cap above the tolerance) and the energy check's
rejected steps.
The energy scale is max(|E₀|, E₀ − min E, m g L) with L the body's largest extent. Writes
bench/results/stability.json and the tables as markdown (bench/results/stability.md).
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings

import numpy as np

from tissue.solver.step_control import MAX_HALVINGS

from .cluster import add_arguments, client, record, run_cells, worker_backend

ROTATIONS = ("large", "polar")
INVERTIBLE = "invertible"   # run on the soft end, the special cells and the impacts
SOFT = (1e2, 1e3)
ALLOWANCE = 0.01            # of the energy scale: the most E − W may rise over its start, bounded
YOUNG = (1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8)
POISSON = (0.0, 0.3, 0.45, 0.49, 0.499)
STEPS = (1e-3, 1e-2, 0.04, 0.1, 0.5)
QUICK = dict(young=(1e2, 1e4, 1e6, 1e8), poisson=(0.0, 0.45, 0.499), dt=(1e-3, 0.04, 0.5))
LENGTH, WIDTH = 0.1, 0.02
BODIES = {"beam": ((LENGTH, WIDTH, WIDTH), (10, 2, 2)),      # size (m), cubes
          "block": ((0.04, 0.04, 0.02), (4, 4, 2)),
          "slab": ((0.1, 0.1, 0.02), (18, 18, 2))}          # (18 + 1)² vertices on each face
TISSUE = dict(young=1e4, poisson=0.45)      # material of the special cells
GRAVITY = (0.0, 0.0, -9.81)
FRICTION = (0.0, 0.1, 0.5, 1.0, 10.0)
SLOPE = 25.0                                # degrees
SLIDE = 0.3                                 # m/s: the block's launch speed along the floor
PRESS = (5e-3, 2.0)                         # the plate's travel (m) and the time it takes (s)
CONTACT_DISTANCE = 2e-3                     # m
# The implicit solve a user gets: the scenes' defaults (scenes/beam.py, liver.py, ...), each step's
# CG to ‖r‖ ≤ 1e-3 ‖b‖ with the multigrid preconditioner, at most 100 iterations, started from the
# last step's solution (tissue.scene.Solver.cg_warm_start).
CG = dict(max_iterations=100, tolerance=1e-3, preconditioner="multigrid", warm_start=True)
STEP_CONTROL = "energy"
ENERGY_BUDGET = True        # the step's end held to its start's energy plus the work done on it


def material_cells(young=YOUNG, poisson=POISSON, dt=STEPS, rotations=ROTATIONS) -> list[dict]:
    return [dict(case="material", young=E, poisson=nu, dt=h, rotation=r)
            for r in rotations for h in dt for E in young for nu in poisson]


def invertible_cells(young=SOFT, poisson=POISSON, dt=STEPS) -> list[dict]:
    """The soft end, the special cells and the contact impacts and jerk with "invertible"."""
    impacts = [c for c in contact_cells((INVERTIBLE,)) if c["case"] in ("impact", "jerk", "rest")]
    return material_cells(young, poisson, dt, (INVERTIBLE,)) + special_cells((INVERTIBLE,)) + impacts


def special_cells(rotations=ROTATIONS) -> list[dict]:
    modes = [("twist", "smooth"), ("twist", "abrupt"), ("inverted", "node"), ("inverted", "mirror"),
             ("impact", "uniform"), ("impact", "random"), ("jerk", "half-length")]
    return [dict(case=c, mode=m, dt=0.04, steps=250, rotation=r) for r in rotations for c, m in modes]


def contact_cells(rotations=ROTATIONS) -> list[dict]:
    """The cells with contact: a cell with a `friction` has obstacles (see `obstacles`)."""
    cells = [dict(case="friction", mode=m, friction=mu, steps=250) for m in ("floor", "slope") for mu in FRICTION]
    cells += [dict(case="press", mode="plate", friction=0.5, steps=100)]
    cells += [dict(case=c, mode=m, friction=0.5, steps=250)
              for c, m in (("impact", "uniform"), ("impact", "random"), ("jerk", "half-length"), ("rest", "clamped"))]
    # The 10 m/s impact at the dt its refusal names (tissue.fem.regime: a node may travel at most
    # the beam's 2 cm thickness in a step): 0.5 s.
    cells += [dict(case="impact", mode="uniform", friction=0.5, steps=250, dt=WIDTH / 10.0)]
    return [dict({"dt": 0.04, **c}, rotation=r) for r in rotations for c in cells]


# ---- scenes ----------------------------------------------------------------------------------

def body_of(cell: dict) -> str:
    return {"friction": "block", "press": "slab"}.get(cell.get("case"), "beam")


def _mesh(body: str = "beam"):
    from tissue.mesh import box

    size, cells = BODIES[body]
    # The beam along +x from its clamped end at x = 0; the others centred above z = 0.
    origin = (0.0, -size[1] / 2, -size[2] / 2) if body == "beam" else (-size[0] / 2, -size[1] / 2, 0.0)
    return box(size, cells, origin)


def _slope():
    """The rotation that turns +z onto the tilted plane's normal (about y, the slope along x)."""
    a = math.radians(SLOPE)
    return np.array([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])


def initial_state(cell: dict, mesh):
    """(positions, velocities, fixed nodes) of a cell."""
    X = mesh.points
    x, v = X.copy(), np.zeros_like(X)
    case, mode = cell["case"], cell.get("mode")
    if body_of(cell) != "beam":                  # free bodies resting on their obstacle
        if mode == "slope":
            x = X @ _slope().T
        elif mode == "floor":
            v[:, 0] = SLIDE
        return x, v, np.zeros(0, dtype=np.int64)
    clamp = np.flatnonzero(X[:, 0] <= 1e-9)
    far = np.flatnonzero(X[:, 0] >= LENGTH - 1e-9)
    fixed = clamp
    if case == "twist":
        fixed = np.concatenate([clamp, far])
        angle = np.pi * (X[:, 0] / LENGTH if mode == "smooth" else (X[:, 0] >= LENGTH - 1e-9))
        c, s = np.cos(angle), np.sin(angle)
        x[:, 1], x[:, 2] = c * X[:, 1] - s * X[:, 2], s * X[:, 1] + c * X[:, 2]
    elif case == "inverted" and mode == "node":
        k = np.argmin(np.linalg.norm(X - [LENGTH / 2, 0, 0], axis=1))   # the centre node, pushed
        x[k, 2] += 1.5 * WIDTH                                           # out through the top face
    elif case == "inverted":
        half = X[:, 0] > LENGTH / 2 + 1e-9
        x[half, 2] *= -1.0
    elif case == "impact" and mode == "uniform":
        v[:, 2] = -10.0
    elif case == "impact":
        v = np.random.default_rng(0).normal(0.0, 5.0, X.shape)
    elif case == "jerk":
        x[clamp, 1] += LENGTH / 2
    v[fixed] = 0.0
    return x, v, fixed


def obstacles(cell: dict, mesh) -> list:
    """The rigid obstacles of a cell: none without `friction`; else a floor under the body's rest
    shape (the slope through the origin), and for the press a plate on the slab's top face."""
    from tissue.contact.obstacles import Box, Plane, RigidObstacle

    if "friction" not in cell:
        return []
    if cell["mode"] == "slope":
        return [RigidObstacle(Plane((0.0, 0.0, 0.0), tuple(_slope()[:, 2])), name="slope")]
    low, high = mesh.points.min(0), mesh.points.max(0)
    out = [RigidObstacle(Plane((0.0, 0.0, low[2])), name="floor")]
    if cell["case"] == "press":
        travel, duration = PRESS
        half = (high[0] - low[0], high[1] - low[1], 0.01)          # twice the slab's top face
        out.append(RigidObstacle(Box((0.0, 0.0, high[2] + half[2]), half), name="plate",
                                 motion=lambda t: np.array([0.0, 0.0, -travel * min(t / duration, 1.0)])))
    return out


_solvers: dict = {}


def solver_for(cell: dict, mesh, material):
    """An ImplicitEuler for the cell, with the scenes' CG (`CG`; a cell's "cg" entry overrides it).
    The rotation and the preconditioner are compiled into the kernels; dt, the stopping rule and
    the material are not: solvers are kept per worker and re-used across cells (a Taichi compile
    costs seconds, a cell a fraction of that)."""
    from tissue import backend
    from tissue.fem import CorotationalFEM
    from tissue.solver import CGSettings, ImplicitEuler
    from tissue.stats import Stats

    cg = CGSettings(**{**CG, **cell.get("cg", {})})
    key = (body_of(cell), cell.get("rotation", "large"), cg.preconditioner)
    entry = _solvers.get(key)
    if entry is None or entry[0] is not backend.current():
        fem = CorotationalFEM(mesh, material, rotation=key[1])
        solver = ImplicitEuler(fem, cell["dt"], gravity=GRAVITY, rayleigh_mass=0.1, rayleigh_stiffness=0.1, cg=cg)
        entry = _solvers[key] = (backend.current(), solver)
    solver = entry[1]
    solver.set_parameters(dt=cell["dt"], cg=cg)     # read at every launch: nothing recompiles
    fem = solver.fem
    fem.model.set_material(material)     # a runtime change: nothing recompiles
    solver.check_regime()                # the refusal a new solver gives at its first step, now
    solver.forget_solves()               # the warm start's last solutions: the last cell's, not this one's
    solver.stats = Stats()
    solver._warned_inversion = False     # the solver warns once per life: here, once per cell
    return solver


def contact_stage(cell: dict, mesh, solver):
    """The contact stage of a cell with obstacles (the scene defaults of tissue.contact.Contact),
    or None. Built after the fixed nodes are set: its compliance leaves them out."""
    from tissue.contact import Contact
    from tissue.contact.pipeline import ContactStage

    found = obstacles(cell, mesh)
    if not found:
        return None
    return ContactStage([solver], found, Contact(friction=cell["friction"], distance=CONTACT_DISTANCE))


def simulate(cell: dict) -> dict:
    """Run one cell on the current backend; return its outcome."""
    from bench.nonlinear_reference import Body, strain_energy
    from tissue.contact.layer import close_budget, obstacle_work
    from tissue.errors import TissueError
    from tissue.fem import Material
    from tissue.mesh.tetmesh import signed_volumes
    from tissue.solver.step_control import EnergyControl

    mesh = _mesh(body_of(cell))
    out = dict(cell)
    start = time.perf_counter()
    try:
        material = Material(cell.get("young", TISSUE["young"]), cell.get("poisson", TISSUE["poisson"]), 1000.0)
        x, v, fixed = initial_state(cell, mesh)
        solver = solver_for(cell, mesh, material)
        solver.set_fixed(fixed)
        solver.set_state(x, v)
        stage = contact_stage(cell, mesh, solver)
    except TissueError as e:
        return {**out, "outcome": "refused", "message": str(e)}
    stepper = EnergyControl(solver, budget=cell.get("energy_budget", ENERGY_BUDGET)) \
        if cell.get("step_control", STEP_CONTROL) == "energy" else solver
    budget = getattr(stepper, "budget", None)
    body = Body(mesh, material, fixed)
    mass = body.lumped_mass
    g = np.asarray(GRAVITY)

    model = "invertible" if cell.get("rotation") == INVERTIBLE else "polar"

    def energy(x, v):
        return 0.5 * mass @ (v * v).sum(1) + strain_energy(body, model, x) - mass @ (x @ g)

    steps = cell.get("steps") or min(1000, max(20, math.ceil(1.0 / cell["dt"])))
    e0 = energy(x, v)
    scale = max(abs(e0), mass.sum() * 9.81 * np.ptp(mesh.points, axis=0).max())
    emax = emin = e0
    out.update(steps=steps, inverted_at_start=int((signed_volumes(x, mesh.tets) <= 0).sum()))
    message, done, e, work, x_start = None, 0, e0, 0.0, x
    inverted_steps, inverted_max = 0, 0      # steps that ended with elements inverted, and the most
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            for done in range(1, steps + 1):
                stepper.step()
                if stage is not None:
                    step_work = obstacle_work(stage.step(), 0)
                    work += step_work
                    if budget:      # the step's end is after the contact correction
                        close_budget(budget, stage.last, 0, stage.settings.tolerance)
                x, v = solver.positions(), solver.velocities()
                if not (np.isfinite(x).all() and np.isfinite(v).all()):
                    break
                flipped = int((signed_volumes(x, mesh.tets) <= 0).sum())
                inverted_steps, inverted_max = inverted_steps + (flipped > 0), max(inverted_max, flipped)
                e = energy(x, v) - work
                emax, emin = max(emax, e), min(emin, e)
                if e - e0 > 1e6 * scale:    # far past bounded: stop early
                    break
        except TissueError as err:
            message = str(err)
    warned = any("elements are inverted" in str(w.message) for w in caught)
    breakdowns = int(sum(solver.stats.history.get("cg_breakdown", [])))
    finite = bool(np.isfinite(x).all() and np.isfinite(v).all())
    inverted = int((signed_volumes(x, mesh.tets) <= 0).sum()) if finite else -1
    scale = max(scale, e0 - emin)
    overshoot, net = (emax - e0) / scale, ((e - e0) / scale if finite else math.nan)
    outcome = classify(message, finite, overshoot, inverted)
    out.update(outcome=outcome, message=message, steps_done=done, energy_overshoot=float(overshoot),
               energy_net=float(net), kinetic_at_end=float(0.5 * mass @ (v * v).sum(1) / scale) if finite else math.nan,
               inverted_at_end=inverted, inverted_steps=inverted_steps, inverted_max=inverted_max,
               inversion_warned=warned, cg_breakdowns=breakdowns,
               **solve_measures(solver), seconds=time.perf_counter() - start)
    if cell["case"] == "material":
        out["self_weight_strain"] = material.density * 9.81 * LENGTH / material.young   # ρ g L / E
    if body_of(cell) == "beam":
        tip = mesh.points[:, 0] >= LENGTH - 1e-9
        out["tip_displacement"] = (x[tip].mean(0) - mesh.points[tip].mean(0)).tolist() if finite else [math.nan] * 3
    else:
        out.update(travel=float(np.linalg.norm(mass @ (x - x_start) / mass.sum())),
                   speed_at_end=float(np.linalg.norm(mass @ v / mass.sum())))
    if stage is not None:
        history = stage.stats.history
        out.update(rows_max=int(max(history["rows"])), contacts_max=int(max(history["contacts"])),
                   gs_iterations_max=int(max(history["gs_iterations"])), gs_residual_max=float(max(history["gs_residual"])),
                   penetration_max=float(max(history["penetration"])), obstacle_work=float(work / scale))
    return out


def solve_measures(solver) -> dict:
    """How far the steps' implicit solves ended from converged: the CG's relative residual
    ‖r‖/‖b‖ (largest, median, at the last step) and the iterations; the steps that ended above
    the stopping rule's tolerance at the iteration cap (unconverged), and those stopped earlier by
    the |pᵀAp| threshold (a body nearly at rest: ‖b‖ tiny); and the energy check's rejected
    steps and the steps it kept gaining at its finest dt (tissue.solver.step_control)."""
    history = solver.stats.history
    residual, iterations = np.asarray(history.get("cg_residual", [])), np.asarray(history.get("cg_iterations", []))
    if not len(residual):
        return {}
    above = residual > solver.cg.tolerance
    at_cap = iterations >= solver.cg.max_iterations
    control = {k: int(sum(history[k])) for k in ("energy_rejections", "energy_unresolved", "budget_projections",
                                                  "budget_unresolved") if k in history}
    if "budget_removed" in history:
        control["budget_removed"] = float(sum(history["budget_removed"]))
    return dict(control, cg_residual=float(residual[-1]), cg_residual_max=float(residual.max()),
                cg_residual_median=float(np.median(residual)), cg_steps=len(residual),
                cg_steps_at_cap=int((above & at_cap).sum()), cg_steps_threshold=int((above & ~at_cap).sum()),
                cg_iterations_max=int(iterations.max()), cg_iterations_median=float(np.median(iterations)))


def classify(message: str | None, finite: bool, overshoot: float, inverted: int) -> str:
    """The outcome of a cell that started stepping (one refused before its first step never gets
    here): `message`, a TissueError raised during the run; `overshoot`, the largest rise of the
    energy less the external work over its start, in energy scales; `inverted`, elements inside
    out at the end."""
    if message is not None:
        return "diverged"
    if not finite:
        return "silent-nan"
    if overshoot > ALLOWANCE:
        return "energy"
    return "inverted" if inverted > 0 else "bounded"


def reclassify(r: dict) -> None:
    """A stored cell's outcome by the current definitions, from its stored measures (a run before
    these definitions called a TissueError during the run "refused" and allowed 100 energy scales)."""
    if "energy_overshoot" not in r:      # refused before its first step, or a task error
        return
    finite = r.get("inverted_at_end", -1) >= 0
    r["outcome"] = classify(r.get("message"), finite, r["energy_overshoot"], max(r.get("inverted_at_end", 0), 0))
    if r["case"] == "material":
        r.setdefault("self_weight_strain", 1000.0 * 9.81 * LENGTH / r["young"])


def refused_by_regime(cell: dict) -> bool:
    """Whether tissue.fem.regime refuses the cell before its first step (no simulation needed)."""
    from tissue.errors import TissueError
    from tissue.fem import Material
    from tissue.fem.regime import check_contact_motion, check_regime

    material = Material(cell.get("young", TISSUE["young"]), cell.get("poisson", TISSUE["poisson"]), 1000.0)
    mesh = _mesh(body_of(cell))
    try:
        check_regime(cell["rotation"], material, GRAVITY, mesh.points)
        if "friction" in cell:
            check_contact_motion(mesh.points, initial_state(cell, mesh)[1], cell["dt"])
    except TissueError:
        return True
    return False


def run_cell(cell: dict) -> dict:
    """A Dask task: initialise this worker's backend, then simulate."""
    worker_backend(cell.get("arch", "cpu"))
    return simulate(cell)


# ---- report ----------------------------------------------------------------------------------

SYMBOL = {"bounded": "✓", "refused": "R", "diverged": "D", "energy": "E", "inverted": "I", "silent-nan": "NaN"}


def symbol(r: dict) -> str:
    """✓, R, D, E (energy gained), NaN, or I for elements left inverted (I⚠ when the solver
    warned about it)."""
    if r.get("outcome") == "inverted" and r.get("inversion_warned"):
        return "I⚠"
    return SYMBOL.get(r.get("outcome"), "error")


def counts(results: list[dict]) -> dict:
    """Cells per outcome, per rotation and in all, with the inverted ones the solver warned about."""
    def tally(cells):
        out = {k: sum(r.get("outcome") == k for r in cells) for k in SYMBOL}
        out.update(cells=len(cells), inverted_warned=sum(r.get("outcome") == "inverted" and bool(r.get("inversion_warned"))
                                                         for r in cells),
                   contact_cells=sum("friction" in r for r in cells),
                   contact_bounded=sum("friction" in r and r.get("outcome") == "bounded" for r in cells),
                   error=sum("error" in r for r in cells))
        return out
    out = tally(results)
    out["by_rotation"] = {rot: tally([r for r in results if r.get("rotation") == rot])
                          for rot in sorted({r.get("rotation") for r in results})}
    return out


TAG = "<!-- figures: bench/results/stability.json -->"   # tests/test_readme_figures.py checks these


# Why the cells that fail fail (docs/stability.md), by rotation and outcome: none fails at
# b0beb68; "invertible" can still carry an element from uncompressed to inverted in one step.
WHY = {("invertible", "inverted"): "a step carried an element past the compression barrier, whose tangent is "
                                   "taken at the step's start (docs/stability.md)"}


def counts_markdown(results: list[dict]) -> list[str]:
    """Cells per outcome and rotation, and why the failing ones fail (`failing`)."""
    tallies = counts(results)
    kinds = ["bounded", "inverted", "energy", "diverged", "refused", "silent-nan"]
    lines = [TAG, "| rotation | cells | " + " | ".join(kinds) + " | contact cells bounded | why the failing fail |",
             "|---|---|" + "---|" * len(kinds) + "---|---|"]
    for name, t in [*tallies["by_rotation"].items(), ("all", tallies)]:
        why = ("see above" if any(f["cells"] > f["bounded"] + f["refused"] for f in tallies["by_rotation"].values())
               else "–") if name == "all" else failing([r for r in results if r.get("rotation") == name])
        lines.append(f"| {name} | {t['cells']} | " + " | ".join(str(t[k]) for k in kinds)
                     + f" | {t['contact_bounded']} of {t['contact_cells']} | {why} |")
    return lines + [""]


def failing(results: list[dict]) -> str:
    """The failing cells of a table row, each group with its reason (`WHY`), or –."""
    groups: dict[str, list[str]] = {}
    for r in results:
        if r.get("outcome") not in ("bounded", "refused"):
            why = WHY.get((r.get("rotation"), r.get("outcome")), "not explained yet")
            groups.setdefault(why, []).append(f"{r['case']} {r.get('mode') or ''}".strip()
                                              + (" onto the floor" if "friction" in r else ""))
    return "; ".join(f"{', '.join(cells)}: {why}" for why, cells in groups.items()) or "–"


def matrix_markdown(results: list[dict]) -> str:
    """The counts, then per rotation a table E × ν: ✓ when bounded at every dt, else the dt that
    were not; the special and contact cells one per row."""
    cells = [r for r in results if r["case"] == "material"]
    lines = counts_markdown(results)
    for rotation in sorted({r["rotation"] for r in cells}):
        mine = [r for r in cells if r["rotation"] == rotation]
        poisson = sorted({r["poisson"] for r in mine})
        steps = sorted({r["dt"] for r in mine})
        lines += [f"**{rotation}** rotation, dt ∈ {{{', '.join(f'{h:g}' for h in steps)}}} s:", "", TAG,
                  "| E (Pa) | ρgL/E | " + " | ".join(f"ν = {nu:g}" for nu in poisson) + " |",
                  "|---|---|" + "---|" * len(poisson)]
        for E in sorted({r["young"] for r in mine}):
            row = []
            for nu in poisson:
                bad = [r for r in mine if r["young"] == E and r["poisson"] == nu and r.get("outcome") != "bounded"]
                every = len(bad) == len(steps) and len({symbol(r) for r in bad}) == 1
                row.append("✓" if not bad else symbol(bad[0]) if every else " ".join(f"{symbol(r)}{r['dt']:g}" for r in bad))
            lines.append(f"| {E:.0e} | {1000 * 9.81 * LENGTH / E:.2g} | " + " | ".join(row) + " |")
        lines += ["", solves_line(mine), ""]
    lines += [TAG, "| special cell (E 1e4, ν 0.45, dt 0.04) | rotation | outcome | inverted start → end | "
              "energy overshoot | CG ‖r‖/‖b‖ max, steps at cap | CG solves | rejected / budget-projected steps | note |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if r["case"] != "material" and "friction" not in r:
            lines.append(f"| {r['case']} {r.get('mode', '')} | {r['rotation']} | {outcome(r)} | "
                         f"{r.get('inverted_at_start', '')} → {r.get('inverted_at_end', '')} | "
                         f"{r.get('energy_overshoot', math.nan):.2g}× | {solves(r)} | {r.get('cg_steps', '–')} | "
                         f"{r.get('energy_rejections', '–')} / {r.get('budget_projections', '–')} | {note(r)} |")
    lines += ["", TAG, "| contact cell (E 1e4, ν 0.45, dt 0.04) | μ | rotation | outcome | inverted start → end | "
              "rows (contacts) | GS its / residual (m) | penetration (mm) | energy overshoot / net / obstacle work | "
              "travel, speed at end | CG ‖r‖/‖b‖ max, steps at cap | note |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "friction" in r and "rows_max" in r:
            motion = (f"{r['travel']:.3g} m, {r['speed_at_end']:.2g} m/s" if "travel" in r else "–")
            lines.append(f"| {r['case']} {r['mode']} | {r['friction']:g} | {r['rotation']} | {outcome(r)} | "
                         f"{r['inverted_at_start']} → {r['inverted_at_end']} | {r['rows_max']} ({r['contacts_max']}) | {r['gs_iterations_max']} / "
                         f"{r['gs_residual_max']:.1e} | {1e3 * r['penetration_max']:.2f} | "
                         f"{r['energy_overshoot']:.2g} / {r['energy_net']:.2g} / {r['obstacle_work']:.2g} | "
                         f"{motion} | {solves(r)} | {note(r)} |")
        elif "friction" in r:
            lines.append(f"| {r['case']} {r.get('mode', '')} | {r['friction']:g} | {r['rotation']} | {outcome(r)} | "
                         f"– | – | – | – | – | – | – | {note(r)} |")
    lines += ["", f"✓ bounded at every dt; a symbol alone: the same outcome at every dt; otherwise the dt (s) of each cell that was not, marked I (elements "
              "left inverted at the end; I⚠: and the solver warned about it), E (the energy rose more than "
              f"{ALLOWANCE:g} of its scale over its start plus the external work), D (diverged: an error during the "
              "run), R (refused with a message before the first step) or NaN (silent non-finite state). Energy "
              "overshoot: the largest rise of the total energy (less the obstacles' work) over its start, net: its "
              "change at the end, obstacle work: the work the moving obstacles did on the body, all in energy "
              "scales. Rows, contacts, GS iterations, residual and penetration: the largest of any step."]
    return "\n".join(lines)


def solves(r: dict) -> str:
    """A cell's largest CG relative residual and its steps that ended above the tolerance at the cap."""
    if "cg_residual_max" not in r:
        return "–"
    return f"{r['cg_residual_max']:.1e}, {r['cg_steps_at_cap']}"


def solves_line(cells: list[dict]) -> str:
    """The implicit solves of a table's cells: the steps that ended above the CG tolerance at the
    cap, the largest relative residual of the others, and the energy check's rejections."""
    measured = [r for r in cells if "cg_steps" in r]
    if not measured:
        return "(no CG residuals recorded for these cells)"
    steps = sum(r["cg_steps"] for r in measured)
    at_cap = sum(r["cg_steps_at_cap"] for r in measured)
    return (f"Implicit solves: {steps:,} CG solves, {at_cap:,} ended above ‖r‖/‖b‖ = {CG['tolerance']:g} at the "
            f"{CG['max_iterations']}-iteration cap; median of the cells' median ‖r‖/‖b‖ "
            f"{np.median([r['cg_residual_median'] for r in measured]):.1e}; the energy check rejected "
            f"{sum(r.get('energy_rejections', 0) for r in measured):,} steps, and kept "
            f"{sum(r.get('energy_unresolved', 0) for r in measured):,} still gaining at dt/{2 ** MAX_HALVINGS}"
            + (f"; the energy budget projected {sum(r.get('budget_projections', 0) for r in measured):,} steps"
               if any("budget_projections" in r for r in measured) else "") + ".")


def outcome(r: dict) -> str:
    """The outcome, with ⚠ where the solver warned about inverted elements."""
    return r.get("outcome", "error") + (" ⚠" if r.get("inversion_warned") else "")


def note(r: dict) -> str:
    """Why a cell failed, or the fields its refusal names (the whole message is in the JSON)."""
    if r.get("outcome") == "refused":
        return f"refused on {r['message'].split(':')[0]}"
    return (r.get("message") or r.get("error") or "")[:80] or WHY.get((r.get("rotation"), r.get("outcome")), "")


def rotations_list(text: str) -> list[str]:
    names = text.split(",")
    unknown = [n for n in names if n not in (*ROTATIONS, INVERTIBLE)]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown rotations {unknown}; expected some of {[*ROTATIONS, INVERTIBLE]}")
    return names


def cell_key(cell: dict) -> tuple:
    """What names a cell (its case, mode, material, dt, rotation and friction)."""
    return tuple(cell.get(k) for k in ("case", "mode", "young", "poisson", "dt", "rotation", "friction"))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_arguments(parser)
    parser.add_argument("--quick", action="store_true", help="a 4 × 3 × 3 material matrix instead of 7 × 5 × 5")
    parser.add_argument("--report", action="store_true", help="rewrite the tables from bench/results/stability.json, "
                        "each cell's outcome classified again from its stored measures by the current definitions")
    parser.add_argument("--only", type=rotations_list, help="run only the cells of these rotations (comma-separated: "
                        "large, polar, invertible) and replace them in bench/results/stability.json, keeping the "
                        "others (and their run's record)")
    parser.add_argument("--cases", type=lambda text: text.split(","), help="run only the cells of these cases "
                        "(comma-separated: material, twist, inverted, impact, jerk, rest, friction, press) and replace "
                        "them in bench/results/stability.json, like --only (both: the cells in both)")
    parser.add_argument("--young", type=lambda text: [float(E) for E in text.split(",")],
                        help="the material cells only at these E (Pa, comma-separated); the others kept")
    parser.add_argument("--material-only", action="store_true", help="only the E × ν × dt cells")
    parser.add_argument("--refused", action="store_true", help="only the cells tissue.fem.regime refuses "
                        "before their first step (cheap: none steps), replaced in stability.json like --only")
    parser.add_argument("--missing", action="store_true", help="only the cells stability.json lacks (added "
                        "to it); with --refused, both")
    parser.add_argument("--out", help="write the cells run to bench/results/OUT.json (and .md) alone, "
                                      "stability.json left as it is (a subset's before/after)")
    parser.add_argument("--step-control", choices=["energy", "none"], default=STEP_CONTROL,
                        help="'none': the ablation without the energy check, written to "
                             "bench/results/stability_unchecked.json (stability.json is left as it is)")
    args = parser.parse_args(argv)
    from .common import RESULTS, write_results

    if args.report:
        data = json.loads((RESULTS / "stability.json").read_text())
        for r in data["cells"]:
            reclassify(r)
        data["counts"] = counts(data["cells"])
        write_results("stability", data)
        table = matrix_markdown(data["cells"])
        (RESULTS / "stability.md").write_text(table + "\n")
        print(table)
        return
    # The longest cells (the press: ~1 s a step) first, so that the workers finish together.
    cells = contact_cells() + special_cells() + (material_cells(**QUICK) if args.quick else material_cells())
    cells += invertible_cells(**({k: QUICK[k] for k in ("poisson", "dt")} if args.quick else {}))
    if args.only:
        cells = [c for c in cells if c["rotation"] in args.only]
    if args.cases:
        cells = [c for c in cells if c["case"] in args.cases]
    if args.young:
        cells = [c for c in cells if c["case"] != "material" or c["young"] in args.young]
    if args.material_only:
        cells = [c for c in cells if c["case"] == "material"]
    if args.refused or args.missing:
        stored = {cell_key(r) for r in json.loads((RESULTS / "stability.json").read_text())["cells"]}
        cells = [c for c in cells if (args.refused and refused_by_regime(c)) or (args.missing and cell_key(c) not in stored)]
    if not cells:
        parser.error("no cells left by --only / --cases")
    for c in cells:
        c.update(arch=args.arch, step_control=args.step_control)
    name = args.out or ("stability" if args.step_control == STEP_CONTROL else "stability_unchecked")
    from bench import stability   # by its module name, so that workers import it (and keep its cache)

    with client(args) as c:
        info = record(c, args)
        results = run_cells(c, stability.run_cell, cells, "stability")
    data = {"machine": info, "cells": results}
    if (args.only or args.cases or args.young or args.refused or args.missing) and name == "stability":
        old = json.loads((RESULTS / "stability.json").read_text())
        records = {k: v for k, v in old.items() if k.startswith("machine")}
        records[f"machine_{'_'.join([*(args.only or []), *(args.cases or []), *map(str, args.young or []), *(['refused'] if args.refused else []), *(['missing'] if args.missing else [])])}"] = info
        rerun = {cell_key(c) for c in cells}
        data = {**records, "cells": [r for r in old["cells"] if cell_key(r) not in rerun] + results}
        for r in data["cells"]:
            reclassify(r)
        results = data["cells"]
    tally = data["counts"] = counts(results)
    print("outcomes:", tally)
    table = matrix_markdown(results)

    write_results(name, data)
    (RESULTS / f"{name}.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
