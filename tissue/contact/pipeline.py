"""The contact stage of a step, run after every soft body's free motion (paper §3, DESIGN step 2-5):

  1. detection    surface vertices within the contact distance of obstacles / other bodies
  2. constraints  H (normal and two tangents per contact, three rows per attachment), δ_free, JDS
  3. compliance   nodal rotations and W = Σ h (H R) A₀⁻¹ (H R)ᵀ ("warped"), or h H A⁻¹ Hᵀ ("exact")
  4. lcp          Coulomb friction by projected block Gauss-Seidel (tissue.contact.frictional_contact),
                  warm-started from the previous step's reactions matched by contact identity;
                  attachments (bilateral) are eliminated first by a Schur complement
  5. correction   x = x_free + R h A₀⁻¹ (H R)ᵀ λ, v = v_free + (x - x_free) / h

λ are impulses (N·s) and δ = δ_free + W λ are positions (see compliance.py); the reaction force
of a contact is λ / h. The frictional contact problem is solved on W / w̄ with w̄ the mean of its
diagonal (reactions w̄ λ in metres), so `tolerance` is in metres: the natural-map residual of the
solver (≈ the worst violation of non-penetration / Coulomb's law, as a displacement).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..mesh import boundary_faces
from ..stats import Stats
from .compliance import ExactCompliance, WarpedCompliance
from .constraints import Attachment, ConstraintRows, JaggedDiagonal, build_rows
from .detection import SAMPLINGS, Contacts, Detector
from .frictional_contact import ContactInfo, FrictionalContactSolver
from .obstacles import RigidObstacle

COMPLIANCES = ("warped", "exact")


@dataclass(frozen=True)
class ContactSettings:
    friction: float = 0.0             # Coulomb μ where neither the obstacle nor the body says
    contact_distance: float = 1e-3    # alarm distance (m): vertices closer than this are constrained
    compliance: str = "warped"        # "warped" (paper §3.2) or "exact" (sparse LU each step)
    tolerance: float = 1e-9           # on the contact solver's residual, in metres (see above)
    max_iterations: int = 200         # Gauss-Seidel sweeps per step
    soft_soft: bool = True            # detect contacts between soft bodies
    sampling: str = "vertices"        # contact points: "vertices", "edges" (+ midpoints), "faces" (+ centroids)
    method: str = "gauss_seidel"      # or "jacobi" (parallel, slower to converge)

    def __post_init__(self):
        if self.sampling not in SAMPLINGS:
            raise TissueError(f"sampling: unknown {self.sampling!r}; expected one of {SAMPLINGS}")
        if self.compliance not in COMPLIANCES:
            raise TissueError(f"compliance: unknown {self.compliance!r}; expected one of {COMPLIANCES}")
        for name in ("friction", "contact_distance", "tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
                raise TissueError(f"{name}: must be a finite number ≥ 0, got {value!r}")
        if self.contact_distance <= 0 or self.tolerance <= 0:
            raise TissueError("contact_distance and tolerance must be > 0")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise TissueError(f"max_iterations: must be an integer ≥ 1, got {self.max_iterations!r}")


@dataclass
class ContactBody:
    """A soft body as the contact stage sees it: its solver, its surface, its friction."""

    solver: object                    # tissue.solver.ImplicitEuler
    surface: np.ndarray | None = None  # boundary triangles (k, 3) as node ids; default: all of them
    friction: float | None = None


@dataclass
class ContactResult:
    """What the last step's contact stage found and applied."""

    contacts: Contacts
    rows: ConstraintRows | None = None
    W: np.ndarray | None = None       # (n_rows, n_rows) Delassus operator (metres per N·s)
    impulses: np.ndarray = field(default_factory=lambda: np.zeros(0))  # λ (n_rows,), N·s
    info: ContactInfo | None = None
    dt: float = 1.0

    @property
    def contact_impulses(self) -> np.ndarray:
        """(k, 3) λ of each contact in its (normal, t1, t2) frame."""
        n = 0 if self.rows is None else self.rows.n_contacts
        return self.impulses[:3 * n].reshape(-1, 3)

    @property
    def contact_forces(self) -> np.ndarray:
        """(k, 3) world reaction force on each contact point (N)."""
        n = 0 if self.rows is None else self.rows.n_contacts
        return np.einsum("ki,kij->kj", self.contact_impulses, self.rows.frames[:n]) / self.dt if n else np.zeros((0, 3))

    @property
    def gaps(self) -> np.ndarray:
        """Linearised constraint values δ = δ_free + W λ after the correction (n_rows,)."""
        return self.rows.q + self.W @ self.impulses if self.rows is not None else np.zeros(0)


class ContactStage:
    """Contact, friction and attachments between soft bodies and rigid obstacles.

    bodies: ContactBody (or bare solvers); obstacles: RigidObstacle; attachments: Attachment.
    Call `step()` after every body has done its free motion (`solver.step()`).
    """

    def __init__(self, bodies, obstacles=(), settings: ContactSettings = ContactSettings(),
                 attachments=(), stats: Stats | None = None):
        self.bodies = [b if isinstance(b, ContactBody) else ContactBody(b) for b in bodies]
        if not self.bodies:
            raise TissueError("contact: needs at least one soft body")
        dts = {b.solver.dt for b in self.bodies}
        if len(dts) != 1:
            raise TissueError(f"contact: the soft bodies must share one time step, got {sorted(dts)}")
        self.dt = dts.pop()
        self.obstacles = list(obstacles)
        for o in self.obstacles:
            if not isinstance(o, RigidObstacle):
                raise TissueError(f"contact: obstacles must be RigidObstacle, got {type(o).__name__}")
        self.attachments = list(attachments)
        for a in self.attachments:
            if not isinstance(a, Attachment):
                raise TissueError(f"contact: attachments must be Attachment, got {type(a).__name__}")
            for b in (a.body, a.other_body):
                if b is not None and not 0 <= b < len(self.bodies):
                    raise TissueError(f"attachment: body {b} out of range [0, {len(self.bodies)})")
        self.settings = settings
        self.stats = stats if stats is not None else Stats()
        surfaces = [b.surface if b.surface is not None else boundary_faces(b.solver.fem.mesh.tets)
                    for b in self.bodies]
        self.detector = Detector(surfaces, self.obstacles, settings.soft_soft, settings.sampling)
        self._fixed = []
        for b in self.bodies:
            mask = np.zeros(b.solver.fem.n_nodes, bool)
            mask[b.solver.fixed_nodes] = True
            self._fixed.append(mask)
        kind = WarpedCompliance if settings.compliance == "warped" else ExactCompliance
        self.compliance = [kind(b.solver) for b in self.bodies]
        self.time = 0.0
        self._warm_keys, self._warm_impulses = np.zeros(0, np.int64), np.zeros((0, 3))
        self.last = ContactResult(Contacts.empty(), dt=self.dt)
        real = backend.current().real
        self._real, self._np = real, (np.float64 if real == ti.f64 else np.float32)

    # ---- queries ------------------------------------------------------------------------------

    def poses(self, time: float):
        return [o.pose(time) for o in self.obstacles]

    def detect(self, distance: float | None = None) -> Contacts:
        """Contacts at the bodies' current positions (e.g. to measure gaps after a step)."""
        poses = self.poses(self.time)
        return self.detector.detect([b.solver.x for b in self.bodies],
                                    self.settings.contact_distance if distance is None else distance, poses, poses)

    def _friction(self, contacts: Contacts) -> np.ndarray:
        default = self.settings.friction
        body_mu = [b.friction for b in self.bodies]
        mu = np.empty(len(contacts))
        for i, (b, o, soft) in enumerate(zip(contacts.body, contacts.other, contacts.soft)):
            if soft:
                pair = [m for m in (body_mu[b], body_mu[o]) if m is not None]
                mu[i] = min(pair) if len(pair) == 2 else default
            else:
                mine = self.obstacles[o].friction
                mu[i] = mine if mine is not None else (body_mu[b] if body_mu[b] is not None else default)
        return mu

    def _drop_fixed(self, contacts: Contacts) -> Contacts:
        """Contacts that cannot move (a point on fixed nodes against a rigid or fixed triangle)
        carry no row."""
        if not any(f.any() for f in self._fixed) or not len(contacts):
            return contacts
        stuck = np.zeros(len(contacts), bool)
        for b, fixed in enumerate(self._fixed):
            sel = np.flatnonzero(contacts.body == b)
            stuck[sel] = (fixed[contacts.nodes[sel]] | (contacts.own_weights[sel] == 0)).all(axis=1)
        for i in np.flatnonzero(stuck & contacts.soft):
            stuck[i] = self._fixed[contacts.other[i]][contacts.triangle[i]].all()
        return contacts.take(~stuck)

    # ---- the step -----------------------------------------------------------------------------

    def step(self, time: float | None = None) -> ContactResult:
        """Detect, solve and correct at the end of the current step (`time`: its end time; by
        default the stage's clock advanced by dt)."""
        s, h, stats = self.settings, self.dt, self.stats
        self.time = self.time + h if time is None else float(time)
        with stats.stage("detection"):
            contacts = self._drop_fixed(self.detector.detect(
                [b.solver.x for b in self.bodies], s.contact_distance, self.poses(self.time),
                self.poses(self.time - h)))
        if not len(contacts) and not self.attachments:
            self._warm_keys, self._warm_impulses = np.zeros(0, np.int64), np.zeros((0, 3))
            self.last = ContactResult(contacts, dt=h)
            for name in ("constraints", "compliance", "lcp", "correction"):   # one entry per step each
                stats.times[name].append(0.0)
            stats.count(contacts=0, rows=0, gs_iterations=0, gs_residual=0.0, penetration=0.0)
            return self.last

        with stats.stage("constraints"):
            free = [b.solver.positions() for b in self.bodies]
            prev = [x - h * b.solver.velocities() for x, b in zip(free, self.bodies)]
            mu = self._friction(contacts)
            rows = build_rows(contacts, free, prev, self.attachments, self.time, frictionless=mu == 0)
            touched = [b for b in range(len(self.bodies)) if np.any(rows.body == b)]
            if s.compliance == "warped":
                jds = {b: JaggedDiagonal(rows, b) for b in touched}

        with stats.stage("compliance"):
            if s.compliance == "warped":
                W = np.zeros((rows.n_rows, rows.n_rows), dtype=self._np)
                for b in touched:
                    c = self.compliance[b]
                    c.update_rotations()
                    c.prepare(jds[b])
                    c.add_to(W)
                W = W.astype(np.float64)
            else:
                W = np.zeros((rows.n_rows, rows.n_rows))
                for b in touched:
                    c = self.compliance[b]
                    c.factorise()
                    c.prepare(rows, b)
                    c.add_to(W)

        with stats.stage("lcp"):
            lam, info = self._solve(W, rows, contacts, mu)

        with stats.stage("correction"):
            for b in touched:
                self.compliance[b].correct(lam)

        nc = rows.n_contacts
        self._warm_keys = contacts.keys()
        self._warm_impulses = np.einsum("ki,kij->kj", lam[:3 * nc].reshape(-1, 3), rows.frames)
        self.last = ContactResult(contacts, rows, W, lam, info, h)
        delta = rows.q + W @ lam
        stats.count(contacts=nc, rows=rows.n_rows, gs_iterations=info.iterations if info else 0,
                    gs_residual=info.residual if info else 0.0,
                    penetration=float(max(0.0, -delta[:3 * nc:3].min())) if nc else 0.0)
        return self.last

    def _solve(self, W: np.ndarray, rows: ConstraintRows, contacts: Contacts, mu: np.ndarray):
        """λ (n_rows,) from δ = W λ + δ_free: attachments eliminated (Schur), then the cone problem."""
        s = self.settings
        m = 3 * rows.n_contacts
        q = rows.q
        lam = np.zeros(rows.n_rows)
        Wc, qc = W[:m, :m].copy(), q[:m]
        if rows.n_rows > m:                 # bilateral rows: δ_b = 0 ⇒ λ_b = -W_bb⁻¹ (q_b + W_bc λ_c)
            bb = scipy.linalg.cho_factor(W[m:, m:])
            Wc = Wc - W[:m, m:] @ scipy.linalg.cho_solve(bb, W[m:, :m])
            qc = qc - W[:m, m:] @ scipy.linalg.cho_solve(bb, q[m:])
        info = None
        if m:
            # Frictionless contacts have empty tangent rows; any positive diagonal there keeps the
            # solver's 3×3 blocks definite (with μ = 0 it never uses them: r_t = 0).
            t = 3 * np.flatnonzero(mu == 0)
            for j in (1, 2):
                Wc[t + j, t + j] = Wc[t, t]
            scale = float(np.mean(np.diag(Wc)))
            warm = np.zeros((rows.n_contacts, 3))
            if len(self._warm_keys):
                keys = contacts.keys()
                pos = np.searchsorted(self._warm_keys, keys)
                pos = np.minimum(pos, len(self._warm_keys) - 1)
                hit = self._warm_keys[pos] == keys
                warm[hit] = np.einsum("kij,kj->ki", rows.frames[hit], self._warm_impulses[pos[hit]])
            solver = FrictionalContactSolver(Wc / scale, mu, s.method)
            r, info = solver.solve(qc, s.tolerance, s.max_iterations, r0=scale * warm.ravel())
            lam[:m] = r / scale
        if rows.n_rows > m:
            lam[m:] = -scipy.linalg.cho_solve(bb, q[m:] + W[m:, :m] @ lam[:m])
        return lam, info
