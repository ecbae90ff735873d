"""The contact stage of a step, run after every soft body's free motion (paper §3, DESIGN step 2-5):

  1. detection    surface vertices within the contact distance of obstacles / other bodies
  2. constraints  H (normal and two tangents per contact, three rows per attachment), δ_free, JDS;
                  H, μ and the JDS are last step's while the contacts are the same ones, on the
                  same triangles at the same weights and normals (a body at rest), δ_free anew
  3. compliance   nodal rotations and W = Σ h (H R) A₀⁻¹ (H R)ᵀ ("warped"), kept as its factors
                  (FactoredDelassus: each body's H R and A₀⁻¹ among the nodes its rows touch; W is
                  formed only when asked for, or with attachments), or h H A⁻¹ Hᵀ ("exact")
  4. lcp          Coulomb friction by projected block Gauss-Seidel, then semi-smooth Newton where
                  the sweeps stall (tissue.contact.frictional_contact, method "auto"),
                  warm-started from the previous step's reactions matched by contact identity;
                  attachments (bilateral) are eliminated first by a Schur complement
  5. correction   x = x_free + R h A₀⁻¹ (H R)ᵀ λ, v = v_free + (x - x_free) / h

Instruments (tissue.haptics): a jaw coupled to a haptic device is one more rigid obstacle for
detection and one more body of one node for steps 2-5 (its blocks of H are minus the row
directions, its compliance h A_hap⁻¹ I₃, its correction a translation); its free motion toward
the device's pose opens the stage.

Kernel launches per step (warped): one detection launch per body (plus one per further body pair
with three or more bodies), one reading its hits out (tissue.contact.hits), one for the rows and
their JDS where they are built anew (tissue.contact.row_writer; without attachments or jaws), one
for W's factors and one for the correction per touched body, one for the Gauss-Seidel; everything
between them is a few dozen numpy operations on arrays of contacts.
Why factors: the contact points outnumber the nodes they move (the pressed liver: 147 contacts, 441
rows, on 54 nodes), so the compliance among those nodes (162², 0.2 MB) is smaller than W (441²,
1.6 MB), and forming W (the paper's kernel 2) is skipped.

λ are impulses (N·s) and δ = δ_free + W λ are positions (see compliance.py); the reaction force
of a contact is λ / h. The frictional contact problem is solved on W / w̄ with w̄ the mean of its
diagonal (reactions w̄ λ in metres), so `tolerance` is in metres: the natural-map residual of the
solver (≈ the worst violation of non-penetration / Coulomb's law, as a displacement).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import scipy.linalg
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem.regime import check_contact_motion
from ..mesh import boundary_faces
from ..options import Options, require, validate
from ..stats import Stats
from .compliance import ExactCompliance
from .warping import WarpedCompliance
from .constraints import Attachment, ConstraintRows, JaggedDiagonal, jacobian, offsets, with_free_values
from .contacts import Contacts
from .detection import Detector
from .delassus import FactoredDelassus
from .frictional_contact import ContactInfo, FrictionalContactSolver, dense_buffer
from .obstacles import RigidObstacle
from .row_writer import RowWriter
from .storage import Storage

# Gauss-Seidel on the contacts in play (FrictionalContactSolver's `reduce`; method 'gauss_seidel'
# only: 'auto' sweeps the whole problem, which cost less on liver_press's problems, side by side)
# costs a fixed price of numpy per solve and saves part of every sweep: the stage uses it after a step that
# took more sweeps than this (the problems change little from one step to the next).
REDUCE_ABOVE = 24


@dataclass
class Contact(Options):
    """Contact and Coulomb friction between every soft body and obstacle: the stage's settings, and
    the option group a scene declares (tissue.contact.layer; `--set contact.distance=...`).

    friction: Coulomb μ where neither the obstacle nor the body says; distance: alarm distance (m),
    surface points closer than this are constrained; compliance: 'warped' (precomputed A₀⁻¹ and
    nodal rotations, the paper's) or 'exact' (a sparse Cholesky per step); tolerance (m, on the
    solver's residual, see above) and max_iterations (sweeps and Newton steps per step): the
    stopping rule; method: 'auto' (Gauss-Seidel, then semi-smooth Newton where the sweeps stall),
    'gauss_seidel', 'newton' or 'jacobi' (parallel, slower to converge); soft_soft: detect contacts between
    soft bodies; sampling: the contact points of each surface ('vertices'; 'edges' and 'faces' add
    edge midpoints and centroids, for obstacles thinner than the mesh spacing); delassus: how the
    warped W is kept, as its factors (per body H R and A₀⁻¹ on the touched nodes), formed
    ('dense'), or 'auto' (factors when smaller than W, see _factors_pay).
    """

    friction: float = 0.3
    distance: float = 3e-3
    compliance: Literal["warped", "exact"] = "warped"
    tolerance: float = 1e-6
    max_iterations: int = 100
    method: Literal["auto", "gauss_seidel", "newton", "jacobi"] = "auto"
    soft_soft: bool = True
    sampling: Literal["vertices", "edges", "faces"] = "vertices"
    delassus: Literal["auto", "factored", "dense"] = "auto"

    def check(self):
        require(self.friction >= 0, "friction", f"must be >= 0, got {self.friction}")
        require(self.distance > 0, "distance", f"must be > 0 m, got {self.distance}")
        require(self.tolerance > 0, "tolerance", f"must be > 0 m, got {self.tolerance}")
        require(self.max_iterations >= 1, "max_iterations", f"must be >= 1, got {self.max_iterations}")


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
    # `rows` and the Delassus operator (metres per N·s; with warped compliance and no attachments
    # its factors, FactoredDelassus, else an (n_rows, n_rows) array): views of buffers the step
    # after next overwrites (copy them to keep them). `W` is the operator as an array.
    rows: ConstraintRows | None = None
    delassus: np.ndarray | FactoredDelassus | None = None
    impulses: np.ndarray = field(default_factory=lambda: np.zeros(0))  # λ (n_rows,), N·s
    info: ContactInfo | None = None
    dt: float = 1.0
    _W: np.ndarray | None = field(default=None, repr=False)

    @property
    def W(self) -> np.ndarray | None:
        """The Delassus operator as an (n_rows, n_rows) array (formed from the factors on first use)."""
        if not isinstance(self.delassus, FactoredDelassus):
            return self.delassus
        if self._W is None:
            self._W = self.delassus.toarray()
        return self._W

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
        return self.rows.q + self.delassus @ self.impulses if self.rows is not None else np.zeros(0)


class ContactStage:
    """Contact, friction and attachments between soft bodies and rigid obstacles.

    bodies: ContactBody (or bare solvers); obstacles: RigidObstacle; attachments: Attachment;
    instruments: rigid tools coupled to a device (tissue.haptics.Instrument): each of their jaws is
    an obstacle for detection and a body of one node for W (its compliance h A_hap⁻¹) and the
    correction; `step()` starts with their free motion toward `instrument.device(time)`.
    Call `step()` after every body has done its free motion (`solver.step()`).
    """

    def __init__(self, bodies, obstacles=(), settings: Contact | None = None, attachments=(),
                 stats: Stats | None = None, instruments=()):
        settings = validate(Contact() if settings is None else settings)
        self.bodies = [b if isinstance(b, ContactBody) else ContactBody(b) for b in bodies]
        if not self.bodies:
            raise TissueError("contact: needs at least one soft body")
        dts = {b.solver.dt for b in self.bodies}
        if len(dts) != 1:
            raise TissueError(f"contact: the soft bodies must share one time step, got {sorted(dts)}")
        self.dt = dts.pop()
        for i, b in enumerate(self.bodies):     # before the first step: what the correction can undo
            check_contact_motion(b.solver.model.points, b.solver.velocities(), self.dt, f"body {i}")
        self.obstacles = list(obstacles)
        for o in self.obstacles:
            if not isinstance(o, RigidObstacle):
                raise TissueError(f"contact: obstacles must be RigidObstacle, got {type(o).__name__}")
        self.instruments = list(instruments)
        self.jaws = [jaw for instrument in self.instruments for jaw in instrument.jaws]
        # Jaw j is obstacle _first_jaw + j, and body len(bodies) + j of the rows.
        self._first_jaw = len(self.obstacles)
        self.obstacles += [jaw.obstacle for jaw in self.jaws]
        self.attachments = list(attachments)
        if settings.delassus == "factored" and self.attachments:
            raise TissueError("delassus: 'factored' cannot take attachments (their Schur complement needs W "
                              "formed); use 'auto' or 'dense'")
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
        self._held_nodes()
        # A topology edit of a body's model (a cut) marks its contact data stale (_follow_edits).
        self._edited: set[int] = set()
        self._held_changed: set[int] = set()    # and one whose held nodes changed (set_fixed)
        self._listeners = [_Edited(self._edited, self._held_changed, b) for b in range(len(self.bodies))]
        for body, listener in zip(self.bodies, self._listeners):
            body.solver.model.subscribe(listener)
        self._pose_cache = {}
        self._buffers, self._flip = [{}, {}], 0
        kind = WarpedCompliance if settings.compliance == "warped" else ExactCompliance
        self.compliance = [kind(b.solver) for b in self.bodies] + self.jaws
        self._lcp = Storage(host=True)          # the frictional problem's arrays, kept between steps
        self._solver = None                     # its solver, renewed each step
        self._storages = [self.detector.storage, self._lcp]
        self._storages += [c.storage for c in self.compliance if isinstance(c, WarpedCompliance)]
        self.time = 0.0
        self._forget_warm_start()
        self._given_mu = None                   # _friction's μ of the bodies and obstacles: as given, as arrays
        self._frictionless = (None, None)       # a μ per contact, and where it is 0 (_solve)
        self._kept = None                       # the last rows' Jacobian (_rows)
        self._writer = RowWriter()              # ... written by one launch (without attachments or jaws)
        self._factors_before = {}               # per body, its last step's factor of W (_factored)
        self.last = ContactResult(Contacts.empty(), dt=self.dt)
        real = backend.current().real
        self._real, self._np = real, (np.float64 if real == ti.f64 else np.float32)

    def _held_nodes(self) -> None:
        self._fixed = []
        for b in self.bodies:
            mask = np.zeros(b.solver.fem.n_nodes, bool)
            mask[b.solver.fixed_nodes] = True
            self._fixed.append(mask)
        # Per-body node arrays side by side (body b's nodes from _offset[b]), for vectorised lookups.
        self._offset = np.r_[0, np.cumsum([len(f) for f in self._fixed])]
        self._fixed_all = np.concatenate(self._fixed)
        # ... and per sample (body b's from _sample_offset[b]) whether it is carried by fixed nodes
        # alone (weights 0 left out): the contacts _drop_fixed looks at
        samples = self.detector.samples
        self._sample_offset = offsets([len(nodes) for nodes, _ in samples])
        self._held_samples = np.concatenate([(fixed[nodes] | (weights == 0)).all(axis=1)
                                             for fixed, (nodes, weights) in zip(self._fixed, samples)])
        self._any_held = bool(self._held_samples.any())

    def _follow_edits(self) -> None:
        """After topology edits (cutting): each edited body's contact surface is its model's
        boundary now (the cut faces included), sampled anew; its compliance follows the model (as
        it does after a change of held nodes alone, which A₀⁻¹ depends on); the held-node masks are
        rebuilt; and the warm start, keyed by sample ids that moved, is dropped. Nothing of the
        previous rows is kept: the next detection builds them on the new surface."""
        for b in sorted(self._edited):
            self.detector.set_surface(b, self.bodies[b].solver.model.boundary_faces())
        for b in sorted(self._edited | self._held_changed):
            self.compliance[b].follow_edits()
        self._edited.clear()
        self._held_changed.clear()
        self._held_nodes()
        self._forget_warm_start()
        self._kept, self._factors_before = None, {}

    def follow_compliance(self, body: int, compliance) -> None:
        """Take body `body`'s rest compliance from a tissue.cutting.CuttingCompliance (kept exact
        through its cuts by low-rank updates) instead of inverting it anew after each cut."""
        self.compliance[body].follow(compliance)
        self._kept = None                       # (its factor's size may change: _KeptRows.factors_pay)
        self._factors_before = {}

    # ---- queries ------------------------------------------------------------------------------

    def poses(self, time: float):
        return [o.pose(time) for o in self.obstacles]

    def detect(self, distance: float | None = None) -> Contacts:
        """Contacts at the bodies' current positions (e.g. to measure gaps after a step)."""
        poses = self.poses(self.time)
        return self.detector.detect([b.solver.x for b in self.bodies],
                                    self.settings.distance if distance is None else distance, poses, poses)

    @property
    def storage_growths(self) -> int:
        """How many times the scratch of the stage's kernels has grown (tissue.contact.storage)."""
        return sum(s.growths for s in self._storages)

    def _given_friction(self) -> tuple:
        """The friction coefficients as given (any of them may be set anew between steps): the
        default, the bodies' and the obstacles'."""
        return (self.settings.friction, tuple(b.friction for b in self.bodies), tuple(o.friction for o in self.obstacles))

    def on_jaws(self, contacts: Contacts) -> np.ndarray:
        """(k,) bool: which of `contacts` touch an instrument's jaw (the obstacles after the scene's)."""
        return ~contacts.soft & (contacts.other >= self._first_jaw)

    def _friction(self, contacts: Contacts, given: tuple | None = None) -> np.ndarray:
        """μ per contact: soft–soft the smaller of the two bodies' (the default unless both say);
        soft–rigid the obstacle's, else the body's, else the default. given: _given_friction()."""
        given = self._given_friction() if given is None else given
        default = given[0]
        if self._given_mu is None or self._given_mu[0] != given:
            body_mu = np.array([np.nan if mu is None else mu for mu in given[1]])
            obstacle_mu = np.array([np.nan if mu is None else mu for mu in given[2]] or [np.nan])
            self._given_mu = (given, body_mu, obstacle_mu, all(mu is None for mu in given[1] + given[2]))
        _, body_mu, obstacle_mu, default_only = self._given_mu
        if default_only:                            # (what the lines below give then)
            return np.full(len(contacts), default, np.float64)
        own = body_mu[contacts.body]
        if not contacts.soft.any():                 # soft–rigid only: the last line's choice made
            other = obstacle_mu[contacts.other]
            return np.where(np.isnan(other), np.where(np.isnan(own), default, own), other)
        other = np.where(contacts.soft, body_mu[np.where(contacts.soft, contacts.other, 0)],
                         obstacle_mu[np.where(contacts.soft, 0, contacts.other)])
        soft = np.where(np.isnan(own) | np.isnan(other), default, np.fmin(own, other))
        rigid = np.where(np.isnan(other), np.where(np.isnan(own), default, own), other)
        return np.where(contacts.soft, soft, rigid)

    def _drop_fixed(self, contacts: Contacts) -> Contacts:
        """Contacts that cannot move (a point on fixed nodes against a rigid or fixed triangle)
        carry no row. (contacts: detection's, whose points are their bodies' samples.)"""
        if not self._any_held or not len(contacts):
            return contacts
        stuck = self._held_samples[self._sample_offset[contacts.body] + contacts.sample]
        if not stuck.any():
            return contacts
        soft = stuck & contacts.soft
        if soft.any():
            tri = self._offset[contacts.other[soft]][:, None] + contacts.triangle[soft]
            stuck[soft] = self._fixed_all[tri].all(axis=1)
        return contacts if not stuck.any() else contacts.take(~stuck)

    def _poses(self, time: float):
        """Obstacle poses at `time` (the last two are kept: a step needs its start and end; not
        with instruments, whose jaws are moved by the contacts after they were asked)."""
        if self.jaws:
            return self.poses(time)
        key = round(time * 1e9)                        # ns: the end of one step is the start of the next
        cached = self._pose_cache.get(key)
        if cached is None:
            cached = self._pose_cache[key] = self.poses(time)
            if len(self._pose_cache) > 2:
                del self._pose_cache[min(self._pose_cache)]     # the earliest time
        return cached

    def _buffer(self, name: str, n: int, dtype, shape=()) -> np.ndarray:
        """A numpy buffer of at least n rows (of `shape`) kept between steps, whole: the same
        memory each step, so the launches writing it replay (tissue.launch). Two sets alternate
        from step to step (`_flip`), so what a step hands out (W, its factors) stays valid until
        the step after next. First made with room for 4n (a press's contacts grow several-fold
        from the first), then doubled: each new buffer records the launches over it again."""
        buffers = self._buffers[self._flip]
        buf = buffers.get(name)
        if buf is None or len(buf) < n or buf.dtype != dtype:
            buf = buffers[name] = np.empty((max(n, 2 * len(buf) if buf is not None else 4 * n, 1),) + shape, dtype)
        return buf

    def _delassus_buffer(self, n: int, dtype) -> np.ndarray:
        """A zeroed (n, n) array in a buffer kept between steps (no page faults per step)."""
        W = self._buffer("W", n * n, dtype)[:n * n].reshape(n, n)
        W.fill(0.0)
        return W

    # ---- the step -----------------------------------------------------------------------------

    def step(self, time: float | None = None) -> ContactResult:
        """Detect, solve and correct at the end of the current step (`time`: its end time; by
        default the stage's clock advanced by dt)."""
        s, h, stats = self.settings, self.dt, self.stats
        self.time = self.time + h if time is None else float(time)
        if self._edited or self._held_changed:
            with stats.stage("topology"):
                self._follow_edits()
        if self.instruments:
            with stats.stage("instruments"):
                for instrument in self.instruments:
                    instrument.free_motion(instrument.device(self.time), h, self.time)
        with stats.stage("detection"):
            contacts = self._drop_fixed(self.detector.detect(
                [b.solver.x for b in self.bodies], s.distance, self._poses(self.time),
                self._poses(self.time - h), velocities=[b.solver.v for b in self.bodies], dt=h))
        if not len(contacts) and not self.attachments:
            self._forget_warm_start()
            self.last = ContactResult(contacts, dt=h)
            for name in ("constraints", "compliance", "lcp", "correction"):   # one entry per step each
                stats.times[name].append(0.0)
            stats.count(contacts=0, rows=0, gs_iterations=0, gs_residual=0.0, penetration=0.0,
                        contact_storage_growths=self.storage_growths)
            return self.last

        keys = self._keys(contacts)
        with stats.stage("constraints"):
            kept, rows = self._rows(contacts, keys)
            mu, touched, jds = kept.mu, kept.touched, kept.jds

        with stats.stage("compliance"):
            self._flip = 1 - self._flip
            if s.compliance == "warped" and kept.factors_pay(self):
                W = self._factored(rows, touched, jds)
            elif s.compliance == "warped":
                self._factors_before = {}
                W = self._delassus_buffer(rows.n_rows, self._np)
                for b in touched:
                    c = self.compliance[b]
                    c.prepare(jds[b])
                    c.add_to(W)
                if W.dtype != np.float64:
                    W = W.astype(np.float64)
            else:
                W = self._delassus_buffer(rows.n_rows, np.float64)
                for b in touched:
                    c = self.compliance[b]
                    c.factorise()
                    c.prepare(rows, b)
                    c.add_to(W)

        with stats.stage("lcp"):
            lam, info = self._solve(W, rows, contacts, mu, keys)

        with stats.stage("correction"):
            for b in touched:
                self.compliance[b].correct(lam)

        nc = rows.n_contacts
        self._warm_keys, self._warm = keys, (rows.frames, lam[:3 * nc].reshape(-1, 3).copy())
        self.last = ContactResult(contacts, rows, W, lam, info, h)
        normal = self._gaps[0::3]                               # δ_n after the correction
        stats.count(contacts=nc, rows=rows.n_rows, gs_iterations=info.iterations if info else 0,
                    gs_residual=info.residual if info else 0.0,
                    penetration=float(max(0.0, -normal.min())) if nc else 0.0,
                    contact_storage_growths=self.storage_growths)
        return self.last

    def _forget_warm_start(self) -> None:
        """No reactions to start the next step's problem from (no contacts, or after an edit)."""
        self._warm_keys, self._warm = np.zeros(0, np.int64), (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        self._last_sweeps = 0

    def _keys(self, contacts: Contacts) -> np.ndarray:
        """contacts.keys(): the kept rows' when detection handed last step's arrays they are made
        from (hits at rest, tissue.contact.hits)."""
        kept = self._kept
        if kept is not None:
            c = kept.contacts
            if contacts.body is c.body and contacts.sample is c.sample and contacts.soft is c.soft \
                    and contacts.other is c.other:
                return kept.keys
        return contacts.keys()

    def _rows(self, contacts: Contacts, keys: np.ndarray) -> tuple["_KeptRows", ConstraintRows]:
        """The step's rows with δ_free, and what is kept of them (_KeptRows: the Jacobian, μ, the
        bodies the rows touch and their JDS): last step's when the contacts are the same ones at
        the same places (`_KeptRows.same`: a body at rest), δ_free anew; else built anew, by one
        launch (tissue.contact.row_writer) or, with attachments or jaws, in numpy."""
        given, attachments = self._given_friction(), tuple(self.attachments)
        kept = self._kept
        if kept is not None and kept.same(contacts, keys, given, attachments):
            return kept, self._with_free_values(kept.rows, contacts)
        mu = self._friction(contacts, given)
        warped = self.settings.compliance == "warped"
        if self.attachments or self.jaws:
            rows = jacobian(contacts, self.attachments, frictionless=mu == 0)
            if self.jaws:
                rows = self._with_jaws(rows, contacts, mu == 0)
            touched = np.bincount(rows.body, minlength=len(self.compliance)).nonzero()[0].tolist()
            jds = {b: JaggedDiagonal(rows, b) for b in touched} if warped else None
            rows = self._with_free_values(rows, contacts)
        else:
            rows, jds = self._writer.write(contacts, mu == 0, self.detector.states, self.detector.state_offset)
            touched = list(jds)
            jds = jds if warped else None
        self._kept = _KeptRows(contacts, keys, given, attachments, rows, mu, touched, jds)
        return self._kept, rows

    def _with_free_values(self, rows: ConstraintRows, contacts: Contacts) -> ConstraintRows:
        """`rows` with δ_free, from the bodies' free and start positions the detection read."""
        states = self.detector.state
        return with_free_values(rows, contacts, [x[:, :3] for x in states], [x[:, 3:] for x in states],
                                self.attachments, self.time)

    def _with_jaws(self, rows: ConstraintRows, contacts: Contacts, frictionless: np.ndarray) -> ConstraintRows:
        """The rows with their blocks on the jaws they touch: minus the row directions (a jaw's
        point moving along d closes the gap), at the jaw's one node (a frictionless contact's
        tangent rows stay empty, as on the soft side)."""
        on = self.on_jaws(contacts).nonzero()[0]
        if not len(on):
            return rows
        jaw = contacts.other[on] - self._first_jaw
        value = rows.frames[on] * np.where(frictionless[on, None, None] & (np.arange(3) > 0)[:, None], 0.0, 1.0)
        return replace(rows, block=np.r_[rows.block, on].astype(np.int32),
                       body=np.r_[rows.body, len(self.bodies) + jaw].astype(np.int32),
                       node=np.r_[rows.node, np.zeros(len(on))].astype(np.int32),
                       value=np.concatenate([rows.value, -value]))

    def _factors_pay(self, rows: ConstraintRows, touched: list[int], jds: dict) -> bool:
        """Whether the warped W is kept as its factors ("auto": when they take at most half of W's
        memory, i.e. contact points outnumber the nodes they move; then a sweep reads the small
        compliances, and refreshing y after an Anderson step costs at most half a dense sweep)."""
        if self.attachments or self.settings.delassus == "dense":
            return False
        if self.settings.delassus == "factored":
            return True
        return 2 * sum(self.compliance[b].factor_size(jds[b]) ** 2 for b in touched) <= rows.n_rows ** 2

    def _factored(self, rows: ConstraintRows, touched: list[int], jds: dict) -> FactoredDelassus:
        """W's factors (FactoredDelassus) from each touched body's warped compliance: their blocks
        ordered by block row (a body's own order within one), one segment per body."""
        parts = []                          # per body: block rows, local node of each block
        for b in touched:
            c, j = self.compliance[b], jds[b]
            c.prepare(j)
            row, local = j.row, j.local
            if c.free:                      # the translation's block per row, at the extra node
                row = np.concatenate([row, j.perm])
                local = np.concatenate([local, np.full(j.n_active, len(j.touched), np.int32)])
            parts.append((row, local, c.factor_size(j)))
        sizes = np.array([d for *_, d in parts])
        y_offset = offsets(sizes)
        q_offset = offsets(sizes ** 2)[:-1]
        row = np.concatenate([p[0] for p in parts])
        col = np.concatenate([y_offset[k] + 3 * p[1] for k, p in enumerate(parts)])
        segment = np.arange(len(parts)).repeat([len(p[0]) for p in parts])
        order = row.argsort(kind="stable")
        n_block_rows = rows.n_rows // 3
        blocks = self._buffer("blocks", len(row), self._np, (3, 3))      # whole buffers: the launches replay
        pos = self._buffer("pos", len(row), np.int32)
        pos[order] = np.arange(len(row))
        total = int(q_offset[-1] + sizes[-1] ** 2)
        Q = self._buffer("Q", total, self._np)
        diagonal = self._buffer("diagonal", n_block_rows, self._np, (3, 3))
        diagonal[:n_block_rows] = 0.0
        start, before = 0, self._factors_before
        self._factors_before = {}
        for k, b in enumerate(touched):
            c = self.compliance[b]
            if isinstance(c, WarpedCompliance):
                c.factor(blocks, Q, diagonal, pos, int(q_offset[k]), start, before.get(b))
                self._factors_before[b] = (Q, int(q_offset[k]), jds[b].touched)
            else:
                c.factor(blocks, Q, diagonal, pos, int(q_offset[k]), start)
            start += len(parts[k][0])
        ptr = offsets(np.bincount(row, minlength=n_block_rows))
        return FactoredDelassus(ptr, col[order], segment[order], blocks[:len(row)].astype(np.float64, copy=False),
                                Q[:total].astype(np.float64, copy=False), y_offset, q_offset,
                                diagonal[:n_block_rows].astype(np.float64, copy=False), scale=self.dt)

    def _solve(self, W, rows: ConstraintRows, contacts: Contacts, mu: np.ndarray, keys: np.ndarray | None = None):
        """λ (n_rows,) from δ = W λ + δ_free: attachments eliminated (Schur; W an array then), then
        the cone problem, warm-started by the contacts' identities (`keys`: contacts.keys(), when
        the caller has them). Leaves the contacts' δ at λ in `_gaps` (3 per contact)."""
        s = self.settings
        m = 3 * rows.n_contacts
        q = rows.q
        lam = np.zeros(rows.n_rows)
        factored = isinstance(W, FactoredDelassus)
        Wc, qc = (W, q) if factored else (W[:m, :m], q[:m])
        if rows.n_rows > m:                 # bilateral rows: δ_b = 0 ⇒ λ_b = -W_bb⁻¹ (q_b + W_bc λ_c)
            bb = scipy.linalg.cho_factor(W[m:, m:])
            Wc = Wc - W[:m, m:] @ scipy.linalg.cho_solve(bb, W[m:, :m])
            qc = qc - W[:m, m:] @ scipy.linalg.cho_solve(bb, q[m:])
        info = None
        if not m:
            self._gaps = np.zeros(0)
        else:
            # The problem on W / w̄ (w̄ the mean of its diagonal). Frictionless contacts have empty
            # tangent rows; any positive diagonal there keeps the solver's 3×3 blocks definite
            # (with μ = 0 it never uses them: r_t = 0).
            if self._frictionless[0] is not mu:             # (μ is the kept rows' at rest)
                self._frictionless = (mu, (mu == 0).nonzero()[0])
            t = self._frictionless[1]
            if factored:
                D = W.diagonal
                if len(t):
                    D = D.copy()
                    D[t, 1, 1] = D[t, 2, 2] = D[t, 0, 0]
                scale = float((D[:, 0, 0] + D[:, 1, 1] + D[:, 2, 2]).sum() / len(D)) / 3.0   # (np.trace's, np.mean's)
                scaled = W.scaled(1.0 / scale, D)
            else:
                diagonal = np.diagonal(Wc).copy()
                for j in (1, 2) if len(t) else ():
                    diagonal[3 * t + j] = diagonal[3 * t]
                scale = float(diagonal.sum()) / m             # (np.mean's sum and division)
                # Where the solver keeps W: it reads it there without a copy.
                scaled = dense_buffer(self._lcp, m)
                np.multiply(Wc, 1.0 / scale, out=scaled)
                for j in (1, 2) if len(t) else ():
                    scaled[3 * t + j, 3 * t + j] = scaled[3 * t, 3 * t]
            keys = contacts.keys() if keys is None else keys
            # From last step's reactions, by contact: as they are where the contacts and their
            # frames are last step's (the rows kept, at rest), else turned into this step's frames.
            frames, local = self._warm
            same = _same_bits(self._warm_keys, keys)
            if same and rows.frames is frames:
                warm = local
            else:
                impulses = np.einsum("ki,kij->kj", local, frames)          # in the world frame
                if same:
                    warm = np.einsum("kij,kj->ki", rows.frames, impulses)
                else:
                    warm = np.zeros((rows.n_contacts, 3))
                    if len(self._warm_keys):
                        pos = self._warm_keys.searchsorted(keys)
                        pos = np.minimum(pos, len(self._warm_keys) - 1)
                        hit = self._warm_keys[pos] == keys
                        warm[hit] = np.einsum("kij,kj->ki", rows.frames[hit], impulses[pos[hit]])
            reduce = self._last_sweeps > REDUCE_ABOVE
            solver = self._solver
            if solver is None or solver.method != s.method:
                solver = self._solver = FrictionalContactSolver(scaled, mu, s.method, check=False, reduce=reduce,
                                                                storage=self._lcp)
            else:
                solver.renew(scaled, mu, reduce)
            r, info = solver.solve(qc, s.tolerance, s.max_iterations, r0=scale * warm.ravel())
            self._last_sweeps = info.iterations
            if not np.isfinite(r).all():        # (W is not checked on the way in: it is ours)
                raise TissueError(f"contact: the frictional contact problem gave non-finite reactions "
                                  f"({rows.n_contacts} contacts); the bodies' state may have diverged (reduce dt)")
            lam[:m] = r / scale
            self._gaps = solver.u
        if rows.n_rows > m:
            lam[m:] = -scipy.linalg.cho_solve(bb, q[m:] + W[m:, :m] @ lam[:m])
        return lam, info


@dataclass
class _KeptRows:
    """The constraint rows' Jacobian of one step's contacts, kept for the next step (see
    ContactStage._rows), and what it was built from."""

    contacts: Contacts
    keys: np.ndarray
    given_friction: tuple
    attachments: tuple
    rows: ConstraintRows          # (their q, δ_free, is the step's: with_free_values writes it anew)
    mu: np.ndarray
    touched: list
    jds: dict | None
    _pays: tuple = (None, False)  # ContactStage._factors_pay's answer for these rows, and the setting it had

    def factors_pay(self, stage: "ContactStage") -> bool:
        """stage._factors_pay for these rows, asked again only when the stage's `delassus` setting
        changed (the rest it reads are the rows, the attachments and the compliances, which a
        stage with other ones does not keep rows across: _follow_edits, follow_compliance)."""
        if self._pays[0] != stage.settings.delassus:
            self._pays = (stage.settings.delassus, stage._factors_pay(self.rows, self.touched, self.jds))
        return self._pays[1]

    def same(self, contacts: Contacts, keys: np.ndarray, given_friction: tuple, attachments: tuple) -> bool:
        """Whether `contacts` and `attachments` give this Jacobian: the same contact points (keys:
        body, sample, kind, other) on the same nodes and triangles, at the same weights and
        normals, bit for bit, the same friction coefficients given and the same attachments."""
        kept = self.contacts
        return given_friction == self.given_friction and attachments == self.attachments and all(
            _same_bits(a, b) for a, b in ((keys, self.keys), (contacts.nodes, kept.nodes),
                                          (contacts.triangle, kept.triangle), (contacts.own_weights, kept.own_weights),
                                          (contacts.weights, kept.weights), (contacts.normal, kept.normal)))


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """a and b hold the same numbers bit for bit (np.array_equal would take -0.0 for 0.0, and
    costs several times more on arrays of a few dozen contacts); the same array (detection's
    hits at rest, kept: tissue.contact.hits) does."""
    return a is b or (a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes())


class _Edited:
    """Marks body `body` stale in `edited` when its model's topology changes, and in `held` when
    its held nodes do (BodyModel.subscribe)."""

    def __init__(self, edited: set, held: set, body: int):
        self.edited, self.held, self.body = edited, held, body

    def topology_changed(self, edit) -> None:
        self.edited.add(self.body)

    def held_changed(self) -> None:
        self.held.add(self.body)
