"""Where one body's free motion gains energy, and why: a scene's body stepped alone (default: the
colon of `organs`, no contact), its steps' energy balance against independent references.

    python -m bench.free_motion_energy [--scene organs] [--body colon] [--steps 100] [--newton]
        [--out free_motion_energy]

The energy E is the energy check's (tissue.solver.step_control): kinetic + elastic (the polar
co-rotational energy) + the potential of gravity, evaluated here in numpy (bench.nonlinear_reference).

1. The solver's own trajectory (`solver.step_control=none`: every step once, the scene's CG). At
   each step, from the step's start (x₀, v₀): the change of E over the solver's step, and over
     - "scipy": the same linearised step solved directly (tissue.solver.reference): CG's share;
     - its balance, exact for a step linearised once (tissue.solver.energy_budget's docstring):
       ΔE = −½ dvᵀM dv − ½ h² v₁ᵀK v₁ − h v₁ᵀB v₁ + N, K = Σ R Kₑ Rᵀ at the start, B the
       Rayleigh damping, N the co-rotational energy's departure from the step's quadratic model
       Ψ(x₀) − f₀·Δx + ½ ΔxᵀK Δx; N split per element (the share of the elements at the held
       nodes; each element's turn over the step, the angle of R₁R₀ᵀ); the principal stretches
       and det F at the step's end (the mesh's largest aspect ratio in "setup");
     - "exact tangent": the same linearised step with K replaced by the exact tangent −∂f/∂x
       (the rotations' derivative included; differenced, bench.nonlinear_reference.tangent) in its
       h² terms (the damping keeps K);
     - "half steps": two linearised steps of dt/2;
     - "newton" (with --newton, ~1 s a step): backward Euler solved by Newton, M (v₁ − v₀) =
       h (f(x₀ + h v₁) + M g − α_M M v₁ − α_K K v₁), to ‖r‖ ≤ 1e-12 of its first (or an update
       at round-off).
2. The same body with other settings, each for the scene's duration: the trajectory's steps that
   gain (> 0, and > the energy check's tolerance of kinetic + elastic), the largest gain; with the
   scene's stepper (the energy check and budget) its rejections, projections and removed energy,
   its CPU ms per step and per simulated second; the mean displacement at the end (what a figure
   shows).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import bench.nonlinear_reference as nl
from bench.common import start_on_cpu, write_results
from tissue.mesh import aspect_ratios

SETTINGS = {      # name: overrides of the scene's solver settings and dt
    "scene": {},
    "cg 1e-10": {"cg_tolerance": 1e-10, "cg_iterations": 1000},
    "dt / 2": {"dt": 0.5},          # dt as a factor of the scene's
    "dt / 4": {"dt": 0.25},
    "rayleigh_stiffness 0.1": {"rayleigh_stiffness": 0.1},
}


def build(scene_name: str, body_name: str, step_control: str, changes: dict):
    """(scene, Body) of one body of the scene, with `changes` to its solver (dt: a factor)."""
    import scenes
    from tissue.body import Body
    from tissue.options import validate

    scene = scenes.load(scene_name)()
    changes = dict(changes)
    if "dt" in changes:
        scene.dt *= changes.pop("dt")
    scene.solver = dataclasses.replace(scene.solver, step_control=step_control, **changes)
    scene = validate(scene)
    return scene, Body(body_name, getattr(scene, body_name), scene)


class Reference:
    """A body's energy and linearised steps in numpy/scipy: its mesh, material and held nodes, the
    step's gravity and Rayleigh damping (α_M, α_K)."""

    def __init__(self, mesh, material, fixed, gravity, rayleigh_mass: float, rayleigh_stiffness: float):
        self.mesh, self.material = mesh, material
        self.nl = nl.Body(mesh, material, np.asarray(fixed, dtype=np.int64))
        self.mass = np.repeat(self.nl.lumped_mass, 3)
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.alpha_m, self.alpha_k = rayleigh_mass, rayleigh_stiffness
        self.held = np.isin(mesh.tets, fixed).any(axis=1)    # elements at a held node

    @classmethod
    def of(cls, scene, body) -> "Reference":
        """The reference of a scene's Body."""
        return cls(body.mesh, body.solver.model.material, body.fixed, scene.gravity, scene.solver.rayleigh_mass,
                   scene.solver.rayleigh_stiffness)

    def inner(self, x, v) -> float:
        """Kinetic + elastic: the energy in play, the scale of the energy check's tolerance."""
        return 0.5 * float(self.mass @ (v * v).ravel()) + nl.strain_energy(self.nl, "polar", x)

    def energy(self, x, v) -> float:
        return self.inner(x, v) - float(self.mass @ (np.tile(self.gravity, len(x)) * x.ravel()))

    def linearise(self, x, v, h):
        from tissue.solver.reference import linearise

        return linearise(self.mesh, self.material, x, v, h, gravity=tuple(self.gravity), rayleigh_mass=self.alpha_m,
                         rayleigh_stiffness=self.alpha_k, rotation="polar")

    def step(self, x, v, h, tangent=None):
        """The linearised step solved directly, `tangent` (default Σ R Kₑ Rᵀ) in its h² terms:
        (x₁, v₁, dv, the linearisation)."""
        lin = self.linearise(x, v, h)
        K = lin.stiffness
        tangent = K if tangent is None else tangent
        A = sp.diags((1 + h * self.alpha_m) * self.mass) + h * self.alpha_k * K + h * h * tangent
        b = h * (lin.forces + self.mass * np.tile(self.gravity, len(x)) - self.alpha_m * self.mass * v.ravel()
                 - self.alpha_k * (K @ v.ravel())) - h * h * (tangent @ v.ravel())
        free = self.nl.free
        dv = np.zeros(len(b))
        dv[free] = spla.spsolve(A.tocsc()[free][:, free], b[free])
        v1 = np.zeros(len(b))
        v1[free] = v.ravel()[free] + dv[free]
        return x + h * v1.reshape(-1, 3), v1.reshape(-1, 3), dv, lin

    def balance(self, x0, v0, h) -> dict:
        """The linearised step's energy balance (module docstring), N per element."""
        x1, v1, dv, lin = self.step(x0, v0, h)
        K, w, dx = lin.stiffness, v1.ravel(), (x1 - x0).ravel()
        tets = self.mesh.tets
        f0, psi0 = nl.corotational_element(self.nl, x0[tets], "polar")
        _, psi1 = nl.corotational_element(self.nl, x1[tets], "polar")
        R0 = nl.polar_rotations(nl.deformation_gradients(self.nl, x0[tets]))
        F1 = nl.deformation_gradients(self.nl, x1[tets])
        R1 = nl.polar_rotations(F1)
        dxe = (x1 - x0)[tets]
        local = np.einsum("mji,maj->mai", R0, dxe).reshape(len(tets), 12)
        departure = psi1 - (psi0 - np.einsum("mai,mai->m", f0, dxe)
                            + 0.5 * np.einsum("mi,mij,mj->m", local, self.nl.Ke, local))
        turn = np.degrees(np.arccos(np.clip((np.einsum("mij,mij->m", R1, R0) - 1) / 2, -1, 1)))
        stretches = np.linalg.svd(F1, compute_uv=False)
        return {"scipy": self.energy(x1, v1) - self.energy(x0, v0),
                "mass": -0.5 * float(dv @ (self.mass * dv)),
                "stiffness": -0.5 * h * h * float(w @ (K @ w)),
                "damping": -h * (self.alpha_m * float(w @ (self.mass * w)) + self.alpha_k * float(w @ (K @ w))),
                "N": float(departure.sum()), "N_held": float(departure[self.held].sum()),
                "turn_median_deg": float(np.median(turn)), "turn_max_deg": float(turn.max()),
                "smallest_stretch": float(stretches.min()), "largest_stretch": float(stretches.max()),
                "smallest_det_F": float(np.linalg.det(F1).min())}

    def newton(self, x0, v0, h, tol=1e-12, max_iterations=30) -> tuple[np.ndarray, np.ndarray, int]:
        """Backward Euler solved by Newton (module docstring): (x₁, v₁, iterations)."""
        K0 = self.linearise(x0, v0, h).stiffness
        free, v = self.nl.free, v0.ravel().copy()
        gravity = self.mass * np.tile(self.gravity, len(x0))
        first, size = None, float(np.ptp(self.mesh.points, axis=0).max())
        for iteration in range(max_iterations):
            x = x0.ravel() + h * v
            f = nl.internal_forces(self.nl, "polar", x.reshape(-1, 3)).ravel()
            r = self.mass * (v - v0.ravel()) - h * (f + gravity - self.alpha_m * self.mass * v
                                                    - self.alpha_k * (K0 @ v))
            norm = np.linalg.norm(r[free])
            first = norm if first is None else first
            if norm <= tol * first:
                break
            J = sp.diags((1 + h * self.alpha_m) * self.mass) + h * h * nl.tangent(self.nl, "polar", x.reshape(-1, 3)) \
                + h * self.alpha_k * K0
            d = np.zeros_like(v)
            d[free] = spla.spsolve(J.tocsc()[free][:, free], -r[free])
            v += d
            if h * np.abs(d).max() <= 1e-13 * size:       # at the round-off floor of ‖r‖
                break
        v1 = np.zeros_like(v)
        v1[free] = v[free]
        return x0 + h * v1.reshape(-1, 3), v1.reshape(-1, 3), iteration + 1


def trajectory(args) -> dict:
    """Part 1 of the module docstring, along the solver's own trajectory."""
    from tissue.solver.step_control import TOLERANCE

    scene, body = build(args.scene, args.body, "none", {})
    ref, solver, h = Reference.of(scene, body), body.solver, scene.dt
    rows = []
    for i in range(args.steps):
        x0, v0 = solver.positions(), solver.velocities()
        e0 = ref.energy(x0, v0)
        solver.step()
        x1, v1 = solver.positions(), solver.velocities()
        row = {"step": i, "kinetic_elastic": max(ref.inner(x0, v0), ref.inner(x1, v1)),
               "solver": ref.energy(x1, v1) - e0}
        row.update(ref.balance(x0, v0, h))
        xt, vt, _, _ = ref.step(x0, v0, h, nl.tangent(ref.nl, "polar", x0))
        row["exact_tangent"] = ref.energy(xt, vt) - e0
        xa, va = x0, v0
        for _ in range(2):
            xa, va, _, _ = ref.step(xa, va, h / 2)
        row["half_steps"] = ref.energy(xa, va) - e0
        if args.newton:
            xn, vn, row["newton_iterations"] = ref.newton(x0, v0, h)
            row["newton"] = ref.energy(xn, vn) - e0
        rows.append(row)
        shown = ("solver", "scipy", "N", "exact_tangent", "half_steps", "newton")
        gains = "  ".join(f"{k} {row[k]:+.2e}" for k in shown if k in row)
        print(f"step {i:3d}: {gains}", flush=True)
    gaining = [r for r in rows if r["solver"] > 0]
    over = [r for r in gaining if r["solver"] > TOLERANCE * r["kinetic_elastic"]]

    def most(key):
        return max(r[key] for r in rows)

    summary = {"steps": len(rows), "gaining_steps": len(gaining), "over_tolerance_steps": len(over),
               "largest_gain": most("solver"),
               "largest_solver_minus_scipy": max(abs(r["solver"] - r["scipy"]) for r in rows),
               "largest_exact_tangent": most("exact_tangent"), "largest_half_steps": most("half_steps"),
               "N_held_share_in_gaining": (sum(r["N_held"] for r in gaining) / sum(r["N"] for r in gaining)
                                           if gaining else None),
               "turn_median_deg_in_gaining": (float(np.median([r["turn_median_deg"] for r in gaining]))
                                              if gaining else None),
               "smallest_stretch": min(r["smallest_stretch"] for r in rows),
               "largest_stretch": most("largest_stretch"),
               "smallest_det_F": min(r["smallest_det_F"] for r in rows)}
    if args.newton:
        summary["largest_newton"] = most("newton")
    if gaining:
        top = max(gaining, key=lambda r: r["solver"])
        summary["largest_gain_step"] = {k: top[k] for k in ("step", "kinetic_elastic", "solver", "scipy", "mass",
                                                            "stiffness", "damping", "N", "N_held", "exact_tangent",
                                                            "half_steps", "turn_median_deg", "turn_max_deg")}
    return {"summary": summary, "steps": rows}


def sweep(args) -> dict:
    """Part 2 of the module docstring."""
    from tissue.solver.step_control import TOLERANCE

    out = {}
    scene, body = build(args.scene, args.body, "energy", {})
    for _ in range(round(scene.duration / scene.dt)):   # compiles the check's and the budget's kernels
        body.stepper.step()
    for name, changes in SETTINGS.items():
        row = {}
        scene, body = build(args.scene, args.body, "none", changes)
        ref = Reference.of(scene, body)
        steps = round(scene.duration / scene.dt)
        gains = []
        for _ in range(steps):
            x0, v0 = body.solver.positions(), body.solver.velocities()
            body.solver.step()
            x1, v1 = body.solver.positions(), body.solver.velocities()
            gains.append((ref.energy(x1, v1) - ref.energy(x0, v0), max(ref.inner(x0, v0), ref.inner(x1, v1))))
        row["steps"] = steps
        row["gaining_steps"] = sum(g > 0 for g, _ in gains)
        row["over_tolerance_steps"] = sum(g > TOLERANCE * scale for g, scale in gains)
        row["largest_gain"] = max(g for g, _ in gains)
        row["gained"] = sum(g for g, _ in gains if g > 0)
        scene, body = build(args.scene, args.body, "energy", changes)
        body.stepper.step()                       # compiles: left out of the time
        started = time.process_time()
        for _ in range(steps - 1):
            body.stepper.step()
        row["cpu_ms_per_step"] = 1e3 * (time.process_time() - started) / (steps - 1)
        row["cpu_ms_per_simulated_second"] = row["cpu_ms_per_step"] * steps / scene.duration
        history = body.solver.stats.history
        for key in ("energy_rejections", "budget_projections", "budget_removed"):
            row[key] = float(np.sum(history.get(key, [])))
        row["mean_displacement_mm"] = 1e3 * float(np.linalg.norm(body.positions() - body.rest, axis=1).mean())
        out[name] = row
        print(f"{name:>24}: " + "  ".join(f"{k} {v:.3g}" for k, v in row.items()), flush=True)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="organs")
    parser.add_argument("--body", default="colon")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--newton", action="store_true", help="also backward Euler solved by Newton (slow)")
    parser.add_argument("--out", default="free_motion_energy")
    args = parser.parse_args(argv)
    info = start_on_cpu()
    scene, body = build(args.scene, args.body, "none", {})
    solver = scene.solver
    setup = {"dt": scene.dt, "duration": scene.duration, "cg_tolerance": solver.cg_tolerance,
             "rayleigh_mass": solver.rayleigh_mass, "rayleigh_stiffness": solver.rayleigh_stiffness,
             "nodes": body.mesh.n_points, "tets": body.mesh.n_tets, "held": len(body.fixed),
             "mass_kg": float(body.solver.model.mass.sum()),
             "largest_aspect_ratio": float(aspect_ratios(body.mesh.points, body.mesh.tets).max())}
    result = {"machine": info, "scene": args.scene, "body": args.body, "setup": setup,
              "load_average_before": os.getloadavg()[0], "trajectory": trajectory(args), "settings": sweep(args),
              "load_average_after": os.getloadavg()[0]}
    print(result["trajectory"]["summary"])
    write_results(args.out, result)


if __name__ == "__main__":
    main()
