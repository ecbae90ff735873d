"""Frictional contact problems in an FCLib-like npz form: generated ones and ones dumped from the
scenes, for bench/contact_solvers.py.

    python -m bench.contact_problems                 # all of them into bench/problems/ (~4 min)
    python -m bench.contact_problems --only generated

A problem file (FCLib's fields, without HDF5): W (3n × 3n, dense, or its CSR arrays W_data,
W_indices, W_indptr), q (3n,), mu (n,), r0 (3n,: the warm start the stage gave it, zeros for the
generated ones), name, source. Per contact the order is (normal, tangent1, tangent2), as in
tissue.contact.frictional_contact. The scene dumps are the stage's own (scaled) problems as it
posed them (tissue.contact.pipeline.ContactStage._solve: W / w̄, reactions in metres), whatever the
solver the run uses; the directory is not committed (a press plate problem is 37 MB).

Generated (rigid bodies, W = J M⁻¹ Jᵀ: more rows than the bodies' dofs, so W is singular):
  stack   a column of boxes on the ground, 4 corner contacts under each (12 rows per 6 dofs);
  pile    a 2-D pyramid of boxes, each on the two below it, 4 contacts per touching pair;
  many    one box resting on the ground through a grid of 10 × 10 contact points (300 rows, 6 dofs).
Dumped:
  press   bench.stability's "press plate" cell (a 3,888-tet slab pressed flat by a plate: 2,382
          rows, 3,465 once pressed), its problems every 10th step;
  liver450  scenes/liver_press with the alarm distance widened to 4 mm (about 450 rows), every
          4th step with at least 420 rows.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from bench.common import ROOT
from tissue.contact.constraints import tangent_frames

PROBLEMS = ROOT / "bench" / "problems"


def save(path: Path, W, q, mu, r0=None, source: str = "") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = dict(q=np.asarray(q, float), mu=np.asarray(mu, float),
                  r0=np.zeros(len(q)) if r0 is None else np.asarray(r0, float), name=path.stem, source=source)
    if sp.issparse(W):
        W = sp.csr_matrix(W)
        arrays.update(W_data=W.data, W_indices=W.indices, W_indptr=W.indptr, W_shape=np.array(W.shape))
    else:
        arrays["W"] = np.asarray(W, float)
    np.savez(path, **arrays)


def load(path: Path) -> dict:
    """{name, source, W (dense or CSR), q, mu, r0}."""
    with np.load(path) as f:
        if "W" in f:
            W = f["W"]
        else:
            W = sp.csr_matrix((f["W_data"], f["W_indices"], f["W_indptr"]), shape=tuple(f["W_shape"]))
        return dict(name=str(f["name"]), source=str(f["source"]), W=W, q=f["q"], mu=f["mu"], r0=f["r0"])


# ---- generated: rigid boxes ---------------------------------------------------------------------

def _skew(p):
    return np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])


def rigid_problem(bodies, contacts, h=0.01, g=9.81, mu=0.5):
    """bodies: (centre, half-extents, mass) of boxes; contacts: (body a, body b or -1 for the
    ground, point, normal pointing into a). Velocity-level problem of one time step from rest:
    u = W r + q with q = J v_free, v_free = h g (falling), r impulses; W = J M⁻¹ Jᵀ."""
    nb = len(bodies)
    Minv = []
    for _, half, m in bodies:
        a, b, c = 2 * np.asarray(half)
        inertia = m / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
        Minv.append(np.r_[np.full(3, 1 / m), 1 / inertia])
    Minv = sp.diags(np.concatenate(Minv))
    J = sp.lil_matrix((3 * len(contacts), 6 * nb))
    for k, (a, b, p, n) in enumerate(contacts):
        F = tangent_frames(np.asarray(n, float)[None])[0]   # the stage's own contact frame
        for body, sign in ((a, 1.0), (b, -1.0)):
            if body < 0:
                continue
            arm = np.asarray(p) - bodies[body][0]
            J[3 * k:3 * k + 3, 6 * body:6 * body + 6] = sign * np.hstack([F, -F @ _skew(arm)])
    J = J.tocsr()
    v = np.zeros(6 * nb)
    v[2::6] = -h * g
    return (J @ Minv @ J.T).tocsr(), J @ v, np.full(len(contacts), mu)


def _corners(centre, half, z, inset=1.0):
    cx, cy = centre[0], centre[1]
    return [np.array([cx + sx * inset * half[0], cy + sy * inset * half[1], z]) for sx in (-1, 1) for sy in (-1, 1)]


def stack(boxes: int = 20):
    half = np.array([0.5, 0.5, 0.5])
    bodies = [(np.array([0.0, 0.0, (2 * i + 1) * half[2]]), half, 1.0) for i in range(boxes)]
    contacts = [(i, i - 1, p, (0, 0, 1)) for i in range(boxes) for p in _corners(bodies[i][0], half, 2 * i * half[2])]
    return rigid_problem(bodies, contacts)


def pile(base: int = 12):
    """Rows of boxes, each row one shorter and shifted by half a box: box (row, j) rests on
    (row - 1, j) and (row - 1, j + 1), two contacts on each (over their overlap)."""
    half = np.array([0.5, 0.5, 0.5])
    index, bodies, contacts = {}, [], []
    for row in range(base):
        for j in range(base - row):
            index[row, j] = len(bodies)
            bodies.append((np.array([j + 0.5 * row, 0.0, (2 * row + 1) * half[2]]), half, 1.0))
    for (row, j), i in index.items():
        x, z = bodies[i][0][0], 2 * row * half[2]
        supports = [(-1, x - 0.5, x + 0.5)] if row == 0 else \
            [(index[row - 1, j], x - 0.5, x), (index[row - 1, j + 1], x, x + 0.5)]
        for other, lo, hi in supports:
            for px in (lo, hi):
                for py in (-half[1], half[1]):
                    contacts.append((i, other, np.array([px, py, z]), (0, 0, 1)))
    return rigid_problem(bodies, contacts)


def many(grid: int = 10):
    half = np.array([1.0, 1.0, 0.2])
    bodies = [(np.array([0.0, 0.0, half[2]]), half, 1.0)]
    s = np.linspace(-half[0], half[0], grid)
    contacts = [(0, -1, np.array([x, y, 0.0]), (0, 0, 1)) for x in s for y in s]
    W, q, mu = rigid_problem(bodies, contacts)
    q = q + np.tile([0.0, 0.05, 0.0], grid * grid)     # and sliding sideways: friction decides
    return W, q, mu


GENERATED = {"stack": stack, "pile": pile, "many": many}


def generate(out: Path = PROBLEMS) -> list[Path]:
    paths = []
    for name, make in GENERATED.items():
        W, q, mu = make()
        # On W / w̄ (w̄ the mean diagonal), as the contact stage poses its problems.
        scale = float(W.diagonal().mean())
        save(out / f"{name}.npz", W / scale, q, mu, source=f"bench.contact_problems.{name}")
        paths.append(out / f"{name}.npz")
    return paths


# ---- dumped from the scenes ---------------------------------------------------------------------

class Recording:
    """While active, every frictional problem the contact stage poses is offered to `keep(index,
    W, q, mu, r0)` (W as an array), then solved as usual."""

    def __init__(self, keep):
        self.keep, self.count = keep, 0

    def __enter__(self):
        import tissue.contact.pipeline as pipeline

        recording, self._original = self, pipeline.FrictionalContactSolver

        class Recorder(self._original):
            def solve(self, q, tol=1e-6, max_iterations=1000, r0=None):
                recording.keep(recording.count, self.W, np.array(q), self.mu.copy(), np.array(r0))
                recording.count += 1
                return super().solve(q, tol, max_iterations, r0)

        pipeline.FrictionalContactSolver = Recorder
        return self

    def __exit__(self, *exc):
        import tissue.contact.pipeline as pipeline

        pipeline.FrictionalContactSolver = self._original


def _dense(W):
    from tissue.contact.delassus import FactoredDelassus

    return W.toarray() if isinstance(W, FactoredDelassus) or sp.issparse(W) else np.array(W)


def dump_press(out: Path = PROBLEMS, every: int = 10, min_rows: int = 1500) -> list[Path]:
    from bench import stability

    cell = next(c for c in stability.contact_cells(("polar",)) if c["case"] == "press")
    paths = []

    def keep(index, W, q, mu, r0):
        if len(q) >= min_rows and index % every == every - 1:
            paths.append(out / f"press_{index:03d}.npz")
            save(paths[-1], _dense(W), q, mu, r0, source=f"bench.stability press plate (polar), step {index + 1}")

    with Recording(keep):
        stability.simulate(cell)
    return paths


def dump_liver450(out: Path = PROBLEMS, every: int = 4, min_rows: int = 420, steps: int = 72) -> list[Path]:
    from bench.contact import WIDE_DISTANCE, press

    sim = press("warped", [f"contact.distance={WIDE_DISTANCE}"])
    paths, seen = [], [0]

    def keep(index, W, q, mu, r0):
        if len(q) >= min_rows:
            seen[0] += 1
            if seen[0] % every == 0:
                paths.append(out / f"liver450_{index:03d}.npz")
                save(paths[-1], _dense(W), q, mu, r0, source=f"scenes/liver_press, distance 4 mm, step {index + 1}")

    with Recording(keep):
        for _ in range(steps):
            sim.step()
    return paths


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("generated", "press", "liver450"))
    parser.add_argument("--out", type=Path, default=PROBLEMS)
    args = parser.parse_args(argv)
    from tissue import backend

    backend.init()
    jobs = {"generated": generate, "liver450": dump_liver450, "press": dump_press}
    for name, job in jobs.items():
        if args.only in (None, name):
            paths = job(args.out)
            print(f"{name}: {len(paths)} problems in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
