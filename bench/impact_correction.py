"""Where the 10 m/s floor impact's energy comes from: the contact correction, with the rest (warped)
or the current (exact) compliance.

    python -m bench.impact_correction [--rotations polar,invertible]

The stability matrix's impact cell (bench/stability.py: the 240-tet cantilever resting on a floor,
10 m/s down, E 1e4 Pa, ν 0.45, dt 0.04 s, 250 steps, the energy check) that tissue.fem.regime now
refuses (|v| dt = 20 times the beam's thickness): its velocity is set after the contact stage is
built, past the refusal. For each compliance: the elastic energy after the first step's free
motion and after its contact correction, the elements inverted then, and the cell's largest energy
overshoot (energy scales, as bench.stability). Writes bench/results/impact_correction.json.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.common import start_on_cpu, write_results


def run(rotation: str, compliance: str) -> dict:
    from bench import stability as s
    from bench.nonlinear_reference import Body, strain_energy
    from tissue.contact import Contact
    from tissue.contact.pipeline import ContactStage
    from tissue.fem import Material
    from tissue.mesh.tetmesh import signed_volumes
    from tissue.solver.step_control import EnergyControl

    cell = dict(case="impact", mode="uniform", friction=0.5, dt=0.04, rotation=rotation)
    mesh = s._mesh("beam")
    material = Material(s.TISSUE["young"], s.TISSUE["poisson"], 1000.0)
    x, v, fixed = s.initial_state(cell, mesh)
    solver = s.solver_for(cell, mesh, material)
    solver.set_fixed(fixed)
    solver.set_state(x, np.zeros_like(v))
    stage = ContactStage([solver], s.obstacles(cell, mesh), Contact(friction=cell["friction"],
                         distance=s.CONTACT_DISTANCE, compliance=compliance))
    solver.set_state(x, v)                  # past the refusal: the cell as it ran before it
    body = Body(mesh, material, fixed)
    mass, g = body.lumped_mass, np.asarray(s.GRAVITY)
    model = "invertible" if rotation == "invertible" else "polar"

    def energy(x, v):
        return 0.5 * mass @ (v * v).sum(1) + strain_energy(body, model, x) - mass @ (x @ g)

    e0 = energy(x, v)
    scale = max(abs(e0), mass.sum() * 9.81 * np.ptp(mesh.points, axis=0).max())
    stepper, emax, out = EnergyControl(solver), e0, dict(rotation=rotation, compliance=compliance)
    for k in range(250):
        stepper.step()
        if k == 0:
            out["elastic_after_free_motion"] = float(strain_energy(body, model, solver.positions()))
        stage.step()
        x, v = solver.positions(), solver.velocities()
        if k == 0:
            out.update(elastic_after_correction=float(strain_energy(body, model, x)),
                       inverted_after_correction=int((signed_volumes(x, mesh.tets) <= 0).sum()))
        emax = max(emax, energy(x, v))
    out.update(energy_overshoot=float((emax - e0) / scale), inverted_at_end=int((signed_volumes(x, mesh.tets) <= 0).sum()))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rotations", default="polar,invertible", type=lambda text: text.split(","))
    args = parser.parse_args(argv)
    info = start_on_cpu()
    rows = []
    for rotation in args.rotations:
        for compliance in ("warped", "exact"):
            rows.append(run(rotation, compliance))
            print(rows[-1], flush=True)
    write_results("impact_correction", dict(machine=info, rows=rows))


if __name__ == "__main__":
    main()
