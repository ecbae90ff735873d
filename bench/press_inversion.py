"""Why `liver_press` run to its end inverts elements of the liver's left lobe (from 2.16 s at
dt 40 ms), and what does not cause it.

The scene is run once to find the first element to invert and the interior node among its corners
("the node"; the scene's mesh: 1072 and 128), then again, recording after each step:

  - the liver's least det F and how many of its elements are inverted;
  - the contacts on the node's elements (a contact point on their nodes, or a point of the stomach
    on a triangle of theirs): how many each detection pass made (soft–soft, or the obstacle's
    name), their least gap at the free positions, their normal force; and the distance from the
    node to the nearest soft–soft contact;
  - the frictional problem's sweeps and residual, and the liver's energy-check rejections and
    energy-budget projections;
  - the warped correction x⁺ − x_free against the exact one for the same impulses, h A⁻¹ Hᵀ λ with
    A the step's own matrix (tissue.contact.compliance.ExactCompliance): its relative error over
    the body, and the least det F had the exact one been applied;
  - the largest angle between two of the rotations of the node's elements at the step's start
    (what the warping's nodal rotation averages, tissue.contact.warping).

Then the scene's variants, each run to its end: the compliance (warped, exact) and dt (40, 20, 10,
5 ms), without soft–soft contact (the stomach not felt), frictionless, with the "invertible"
rotation, and with the probe's push stopped at 2.0 s or 1.8 s (5 and 4.5 cm, the same path and
speed until then), then held: the first time an element is inverted, the least det F over the run, the elements
inverted at the end. No timing.

    python -m bench.press_inversion [--out lobe_press_inversion]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from bench.common import start_on_cpu, write_results
from bench.contact import contact_stage, press


def stopped_at(seconds: float) -> str:
    """The probe's keyframes override that ends its push at `seconds`, on the same path at the same
    speed until then (a shorter push), and holds it there."""
    from scenes.liver_press import PUSH_TIME, LiverPress

    end = LiverPress().probe.keyframes[5:]
    return "probe.keyframes=" + ",".join(str(v) for v in (0, 0, 0, 0, seconds, *(c * seconds / PUSH_TIME for c in end)))


VARIANTS = {
    "warped, dt 40 ms (the scene)": ("warped", []),
    "exact, dt 40 ms": ("exact", []),
    "warped, dt 20 ms": ("warped", ["dt=0.02"]),
    "warped, dt 10 ms": ("warped", ["dt=0.01"]),
    "exact, dt 10 ms": ("exact", ["dt=0.01"]),
    "exact, dt 5 ms": ("exact", ["dt=0.005"]),
    "warped, no soft-soft contact": ("warped", ["contact.soft_soft=false"]),
    "warped, frictionless": ("warped", ["contact.friction=0"]),
    "warped, rotation invertible": ("warped", ["liver.rotation=invertible"]),
    "warped, the push stopped at 2.0 s": ("warped", [stopped_at(2.0)]),
    "warped, the push stopped at 1.8 s": ("warped", [stopped_at(1.8)]),
}


def det_f(body, x: np.ndarray) -> np.ndarray:
    """det F of each element of `body` at positions x: its signed volume over its rest volume."""
    from tissue.mesh.tetmesh import signed_volumes

    return signed_volumes(x, body.mesh.tets) / signed_volumes(body.rest, body.mesh.tets)


def run_variant(compliance: str, overrides: list[str]) -> dict:
    """The scene with these settings to its end: the first inversion, the least det F, the end."""
    sim = press(compliance, overrides)
    liver = sim.bodies["liver"]
    first, least, first_element = None, np.inf, None
    for _ in range(sim.scene.steps):
        sim.step()
        d = det_f(liver, liver.positions())
        least = min(least, float(d.min()))
        if first is None and (d <= 0).any():
            first, first_element = round(sim.time, 4), int(d.argmin())
    return {"first_inversion_s": first, "first_inverted_element": first_element, "least_det_f": least,
            "det_f_at_end": float(d.min()), "inverted_at_end": int((d <= 0).sum()),
            "dt": sim.scene.dt, "steps": sim.step_count}


def the_node(body, element: int) -> int:
    """The corner of `element` inside the body (not on its boundary)."""
    surface = np.unique(body.faces)
    inside = [int(n) for n in body.mesh.tets[element] if n not in surface]
    return inside[0]


def opposite_heights(body, element: int) -> dict:
    """Rest height (m) of each corner of `element` over the plane of the other three."""
    tet, X = body.mesh.tets[element], body.rest
    out = {}
    for k in range(4):
        a, b, c = X[np.delete(tet, k)]
        n = np.cross(b - a, c - a)
        out[str(int(tet[k]))] = float(abs((X[tet[k]] - a) @ n) / np.linalg.norm(n))
    return out


def largest_angle(rotations: np.ndarray) -> float:
    """The largest angle (degrees) between two of the rotations (k, 3, 3)."""
    relative = np.einsum("aji,bjk->abik", rotations, rotations)
    cosine = (np.trace(relative, axis1=2, axis2=3) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))).max())


def diagnose(element: int) -> dict:
    """The scene's run, step by step, around the interior node of `element` (module docstring)."""
    from tissue.contact.compliance import ExactCompliance
    from tissue.contact.layer import correction_impulses
    from tissue.solver.reference import element_rotations

    sim = press("warped")
    liver = sim.bodies["liver"]
    names = list(sim.bodies)
    body = names.index("liver")
    stage = contact_stage(sim)
    obstacles = [o.name for o in stage.obstacles]
    solver, tets, n = liver.solver, liver.mesh.tets, liver.mesh.n_points
    node = the_node(liver, element)
    around = np.flatnonzero((tets == node).any(axis=1))
    near = np.zeros(n, bool)
    near[tets[around]] = True
    exact = ExactCompliance(solver)
    free = {}
    contact_step = stage.step

    def step(time=None):                    # the free positions and the step's exact matrix, first
        free["x"], free["v"] = liver.positions(), liver.velocities()
        exact.factorise()
        return contact_step(time=time)

    stage.step = step
    out = {"element": element, "element_corners": tets[element].tolist(), "node": node,
           "elements_around_node": around.tolist(), "n_elements_around_node": len(around),
           "rest_heights_m": opposite_heights(liver, element), "steps": []}
    for _ in range(sim.scene.steps):
        sim.step()
        x, x_free, result = liver.positions(), free["x"], stage.last
        c, h = result.contacts, result.dt
        own = (c.body == body) & (near[np.where((c.body == body)[:, None], c.nodes, 0)] & (c.own_weights > 0)).any(axis=1)
        theirs = (c.soft & (c.other == body) & (near[np.maximum(c.triangle, 0)] & (c.weights > 0)).any(axis=1))
        on_node = own | theirs
        passes = {}
        for i in on_node.nonzero()[0]:
            kind = "soft-soft" if c.soft[i] else obstacles[c.other[i]]
            passes[kind] = passes.get(kind, 0) + 1
        soft_on_liver = c.soft & ((c.body == body) | (c.other == body))
        impulses = result.contact_impulses
        dx = np.zeros(3 * n)
        dx[exact.free] = h * exact._solve(correction_impulses(result, body, n).reshape(-1)[exact.free])
        dx = dx.reshape(-1, 3)
        warped = x - x_free
        start = x_free - h * free["v"]
        d = det_f(liver, x)
        history = sim.stats.history
        out["steps"].append({
            "time": round(sim.time, 4), "least_det_f": float(d.min()), "inverted": int((d <= 0).sum()),
            "det_f_first_element": float(d[element]),
            "contacts_on_node_elements": passes,
            "least_free_gap_on_node_elements": float(c.gap[on_node].min()) if on_node.any() else None,
            "normal_force_on_node_elements": float(impulses[on_node[:len(impulses)], 0].sum() / h),
            "nearest_soft_contact_to_node": (float(np.linalg.norm(c.closest[soft_on_liver] - x[node], axis=1).min())
                                             if soft_on_liver.any() else None),
            "gs_iterations": result.info.iterations if result.info else 0,
            "gs_residual": result.info.residual if result.info else 0.0,
            "energy_rejections": int(history["liver.energy_rejections"][-1]),
            "budget_projections": int(history["liver.budget_projections"][-1]),
            "warping_error": float(np.linalg.norm(warped - dx) / max(np.linalg.norm(dx), 1e-300)),
            "correction_at_node": float(np.linalg.norm(warped[node])),
            "least_det_f_exact_correction": float(det_f(liver, x_free + dx).min()),
            "rotation_spread_deg": largest_angle(element_rotations(liver.mesh, start, solver.fem.rotation)[around]),
        })
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="lobe_press_inversion")
    args = parser.parse_args(argv)
    info = start_on_cpu()
    warnings.filterwarnings("ignore", message=".*elements are inverted")     # what this counts
    variants = {}
    for label, (compliance, overrides) in VARIANTS.items():
        started = time.perf_counter()
        variants[label] = {"compliance": compliance, "overrides": overrides, **run_variant(compliance, overrides)}
        v = variants[label]
        print(f"{label:36s} first inversion {v['first_inversion_s']} s, least det F {v['least_det_f']:.3f}, "
              f"at the end {v['det_f_at_end']:.3f} ({v['inverted_at_end']} inverted)  "
              f"[{time.perf_counter() - started:.0f} s]", flush=True)
    element = variants["warped, dt 40 ms (the scene)"]["first_inverted_element"]
    steps = diagnose(element)
    for s in steps["steps"]:
        print(f"t {s['time']:.2f}  det F {s['least_det_f']:7.3f} ({s['inverted']:2d} inverted), element {element} "
              f"{s['det_f_first_element']:7.3f}  contacts {s['contacts_on_node_elements']}  "
              f"warping error {s['warping_error']:.2f}  exact correction's det F {s['least_det_f_exact_correction']:7.3f}  "
              f"rotations {s['rotation_spread_deg']:4.0f}°  GS {s['gs_iterations']} ({s['gs_residual']:.1e})")
    write_results(args.out, {"machine": info, "variants": variants, "scene_run": steps})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
