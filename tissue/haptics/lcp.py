"""The haptic loop's contact problem: one simulation step's LCP restricted to the instrument's rows
and the rows coupled to them, and its re-solve for a new device pose (paper §3.6, Saupin 2008).

Restriction (`restrict`). After a step, the problem is δ = δ_free + W λ over all rows (the contact
stage's, W with the jaws' compliance h A_hap⁻¹ in it). The haptic loop keeps the contacts on the
jaws and the contacts in play (pushed, λ ≠ 0, or touching, δ_n ≤ 0), the jaws' first, up to
`max_contacts`; the impulses of the contacts left out are held at the step's λ and folded into
δ_free (δ_free,sel += W_sel,rest λ_rest: exact while they stay so). Contacts apart with λ = 0 on
other bodies stay apart (they can only close if the re-solve moves the body more than their gap
within one step).

Re-solve (`HapticSolver`). Between steps the device moves: each jaw's target moves by Δⱼ, its
free position by gⱼ Δⱼ (gⱼ = ∂x_free/∂x_d, tissue.haptics.instrument.Coupling.follow), so
δ_free' = δ_free + Σⱼ Jⱼ gⱼ Δⱼ (Jⱼ: the rows' blocks on jaw j): the step redone with the device
where it is now (the paper's scheme), the bodies' own motion since the step left out. (Adding it,
as a first-order prediction of the next step from the velocities after this one, made the force
at a step boundary jump more, not less, on a probe pressed into a block: measured, dropped.) Projected Gauss-Seidel with
Coulomb friction (the contact stage's exact 3×3 local solve) from the last λ, at most
`max_sweeps` sweeps: a bounded time per tick. The jaw then sits at
xⱼ' = xⱼ⁺ + gⱼ Δⱼ + h A⁻¹ Jⱼᵀ (λ' - λ) and the device renders the springs' force
Σ K (xⱼ' - x_dⱼ').

Compiled once: one Taichi kernel over numpy buffers of a fixed capacity (the problem's size is a
number in the buffers, not an argument), launched by replaying its recorded context
(tissue.launch): a tick costs the sweeps and a replayed launch, not Taichi's setting of every array
argument. Why not numpy: a sweep is sequential (contact after contact), so in Python every
contact pays the interpreter, and a sweep over tens of contacts would take much of a tick
(bench/haptics times a re-solve).
"""


from dataclasses import dataclass

import numpy as np
import taichi as ti

from ..contact.delassus import FactoredDelassus
from ..contact.cone import contact_error2, local_solve, vector_at
from ..errors import TissueError
from ..launch import replayed

MAX_CONTACTS = 128       # the largest restricted problem (rows: 3×)
MAX_JAWS = 2
MAX_SWEEPS = 30          # per tick (bounded time; the next tick continues from this one's λ)
TOLERANCE = 1e-7         # m: the natural-map residual of the problem on W / w̄ (as the stage's)


@dataclass
class HapticProblem:
    """One step's restricted problem and the instrument's state after it (all float64 arrays).

    W (3n, 3n), q = δ_free (3n), lam (3n, the step's λ), mu (n), J (3n, 3 jaws): the rows'
    blocks on each jaw; per jaw: follow g, compliance h/A, stiffness K, position x⁺ and target
    after the step, offset and opening axis (target = p + R (offset + jaw/2 · axis)); the device
    pose the step used; step number, its end time, h."""

    step: int
    time: float
    h: float
    W: np.ndarray
    q: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    J: np.ndarray
    follow: np.ndarray
    compliance: np.ndarray
    stiffness: np.ndarray
    x: np.ndarray
    target: np.ndarray
    offset: np.ndarray
    axis: np.ndarray
    device_position: np.ndarray
    device_orientation: np.ndarray
    device_jaw: float

    @property
    def n(self) -> int:
        return len(self.mu)

    @property
    def jaws(self) -> int:
        return len(self.x)

    def targets(self, position, orientation, jaw: float) -> np.ndarray:
        """(jaws, 3) the jaws' targets for a device pose."""
        return np.asarray(position) + (self.offset + 0.5 * jaw * self.axis) @ np.asarray(orientation).T


def restrict(stage, step: int = 0, max_contacts: int = MAX_CONTACTS) -> HapticProblem:
    """The contact stage's last problem restricted to its instrument (see the module docstring)."""
    jaws = stage.jaws
    if not jaws or len(jaws) > MAX_JAWS:
        raise TissueError(f"haptics: the contact stage must hold an instrument of 1 to {MAX_JAWS} jaws, "
                          f"got {len(jaws)} jaws")
    last, h = stage.last, stage.dt
    rows = last.rows
    k = 0 if rows is None else rows.n_contacts
    nb = len(stage.bodies)
    sel = np.zeros(0, np.int64)
    W, J = np.zeros((0, 0)), np.zeros((0, 3 * len(jaws)))
    q = lam = mu = np.zeros(0)
    if k:
        lam_all = last.impulses[:3 * k]
        on_jaw = np.zeros(k, bool)
        jaw_entries = np.flatnonzero(rows.body >= nb)
        on_jaw[rows.block[jaw_entries]] = True
        L = lam_all.reshape(-1, 3)
        gaps = np.asarray(last.gaps[:3 * k])[0::3]
        in_play = (L != 0).any(axis=1) | (gaps <= 0)
        others = np.flatnonzero(in_play & ~on_jaw)
        others = others[np.argsort(-L[others, 0], kind="stable")]
        sel = np.r_[np.flatnonzero(on_jaw), others][:max_contacts]
        dofs = (3 * sel[:, None] + np.arange(3)).ravel()
        Wfull = last.delassus
        W = Wfull.restricted(sel) if isinstance(Wfull, FactoredDelassus) else np.array(Wfull[np.ix_(dofs, dofs)])
        q = rows.q[dofs].astype(np.float64)
        held = lam_all.copy()
        held[dofs] = 0.0
        if held.any():                          # contacts left out keep their λ: fold it into δ_free
            full = np.zeros(rows.n_rows)
            full[:3 * k] = held
            q = q + (Wfull @ full)[dofs]
        lam = lam_all[dofs].astype(np.float64)
        mu = stage._friction(last.contacts)[sel].astype(np.float64)
        position = np.full(k, -1)
        position[sel] = np.arange(len(sel))
        J = np.zeros((3 * len(sel), 3 * len(jaws)))
        for e in jaw_entries:
            i = position[rows.block[e]]
            if i >= 0:
                j = rows.body[e] - nb
                J[3 * i:3 * i + 3, 3 * j:3 * j + 3] = rows.value[e]
    pose = stage.instruments[0].pose
    return HapticProblem(
        step=step, time=stage.time, h=h, W=W, q=q, lam=lam, mu=mu, J=J,
        follow=np.array([j.coupling.follow(h) for j in jaws]), compliance=np.array([j.compliance() for j in jaws]),
        stiffness=np.array([j.coupling.stiffness for j in jaws]), x=np.array([j.x for j in jaws]),
        target=np.array([j.target for j in jaws]), offset=np.array([j.offset for j in jaws]),
        axis=np.array([j.opening_axis for j in jaws]), device_position=np.array(pose.position, dtype=np.float64),
        device_orientation=np.array(pose.orientation, dtype=np.float64), device_jaw=float(pose.jaw))


# io buffer slots: inputs, then outputs
N, JAWS, SWEEPS, TOL2, DX = 0, 1, 2, 3, 4            # DX: 3 per jaw (g Δ, m)
OUT_SWEEPS, OUT_ERROR2, OUT_IMPULSE = 10, 11, 12     # OUT_IMPULSE: 3 per jaw (Jᵀ r, scaled)
IO_SIZE = 18


@ti.func
def _add_column(Wt: ti.template(), u: ti.template(), m, k, d):
    """u += W[:, contact k's columns] d, skipped for d = 0 (a contact apart that stays apart)."""
    if d[0] != 0.0 or d[1] != 0.0 or d[2] != 0.0:
        for l in range(m):
            u[l] += Wt[3 * k, l] * d[0] + Wt[3 * k + 1, l] * d[1] + Wt[3 * k + 2, l] * d[2]


@ti.kernel
def _resolve(Wt: ti.types.ndarray(ndim=2), q: ti.types.ndarray(ndim=1), J: ti.types.ndarray(ndim=2),
             mu: ti.types.ndarray(ndim=1), r: ti.types.ndarray(ndim=1), u: ti.types.ndarray(ndim=1),
             io: ti.types.ndarray(ndim=1)):
    """Gauss-Seidel on u = (q + J dx) + W r from r, on one thread (see the module docstring).

    Wt is W transposed (W's columns as rows). u is kept up to date as r changes, column by column:
    most restricted contacts are apart (r = 0) and stay so, and those cost a sweep their 3×3 solve
    only, instead of a row of W each (the sum u_i = (q + J dx)_i + W_i r, what the sweep computed
    before, in another order)."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        n, jaws, max_sweeps = ti.cast(io[N], ti.i32), ti.cast(io[JAWS], ti.i32), ti.cast(io[SWEEPS], ti.i32)
        m = 3 * n
        for l in range(m):
            s = q[l]
            for c in range(3 * jaws):
                s += J[l, c] * io[DX + c]
            u[l] = s
        for k in range(n):
            _add_column(Wt, u, m, k, vector_at(r, k))
        sweeps, est = 0, 0.0
        while sweeps < max_sweeps:
            est = 0.0
            for i in range(n):
                ui, ri = vector_at(u, i), vector_at(r, i)
                if ri[0] != 0.0 or ri[1] != 0.0 or ri[2] != 0.0 or ui[0] < 0.0:   # else apart, and stays so
                    A = ti.Matrix.zero(float, 3, 3)
                    for a, b in ti.static(ti.ndrange(3, 3)):
                        A[a, b] = Wt[3 * i + b, 3 * i + a]
                    est += contact_error2(ri, ui, mu[i])
                    rnew = local_solve(A, ui - A @ ri, mu[i])
                    _add_column(Wt, u, m, i, rnew - ri)
                    for a in ti.static(range(3)):
                        r[3 * i + a] = rnew[a]
            sweeps += 1
            if est <= io[TOL2]:
                break
        io[OUT_SWEEPS] = sweeps
        io[OUT_ERROR2] = est
        for c in range(3 * jaws):
            s = 0.0
            for l in range(m):
                s += J[l, c] * r[l]
            io[OUT_IMPULSE + c] = s


RESOLVE = replayed(_resolve)


@dataclass
class HapticForce:
    """What one tick renders: the force on the device (the springs', N), the grip (N), the
    contacts' force on the jaws (N), the jaws' positions, sweeps, the residual estimate (m), each
    jaw's spring force (jaws, 3; N) and the part of each that is a blended-in correction
    (tissue.haptics.continuity; jaws × 3, N)."""

    force: np.ndarray
    grip: float
    contact: np.ndarray
    jaws: np.ndarray
    sweeps: int
    residual: float
    springs: np.ndarray
    correction: np.ndarray

    @staticmethod
    def of_springs(springs: np.ndarray, axes: np.ndarray, **rest) -> "HapticForce":
        """The device's force and grip from the jaws' springs (axes: the jaws' opening axes in the world)."""
        grip = 0.5 * float(np.einsum("ja,ja->", springs, axes))
        return HapticForce(force=springs.sum(axis=0), grip=grip, springs=springs, **rest)

    def shifted(self, offset: np.ndarray, axes: np.ndarray) -> "HapticForce":
        """This force with `offset` (jaws, 3; N) added to the jaws' springs."""
        return HapticForce.of_springs(self.springs + offset, axes, contact=self.contact, jaws=self.jaws,
                                      sweeps=self.sweeps, residual=self.residual,
                                      correction=self.correction + offset)


class HapticSolver:
    """The re-solve of a HapticProblem for new device poses, on buffers of a fixed capacity
    (compiled once; `warm()` runs it once before a clock starts)."""

    def __init__(self, max_contacts: int = MAX_CONTACTS, max_sweeps: int = MAX_SWEEPS, tolerance: float = TOLERANCE):
        m = 3 * max_contacts
        self.capacity, self.max_sweeps, self.tolerance = max_contacts, int(max_sweeps), float(tolerance)
        self.Wt, self.q, self.r, self.u = np.zeros((m, m)), np.zeros(m), np.zeros(m), np.zeros(m)   # Wt: W transposed
        self.J, self.mu = np.zeros((m, 3 * MAX_JAWS)), np.zeros(max_contacts)
        self.io = np.zeros(IO_SIZE)
        self.problem, self.scale = None, 1.0

    def load(self, problem: HapticProblem) -> None:
        """Take a new step's problem; the next solve starts from its λ."""
        n, m = problem.n, 3 * problem.n
        if n > self.capacity:
            raise TissueError(f"haptics: {n} contacts exceed the haptic solver's capacity {self.capacity}")
        # The problem on W / w̄ (w̄ the mean of its diagonal), reactions w̄ λ in metres, as the stage's.
        self.scale = float(np.mean(np.diagonal(problem.W))) if n else 1.0
        self.Wt[:m, :m] = problem.W.T / self.scale
        t = np.flatnonzero(problem.mu == 0)             # frictionless: any positive tangent diagonal
        for j in (1, 2):
            self.Wt[3 * t + j, 3 * t + j] = self.Wt[3 * t, 3 * t]
        self.q[:m], self.r[:m], self.mu[:n] = problem.q, problem.lam * self.scale, problem.mu
        self.J[:m, :3 * problem.jaws] = problem.J
        self.io[:] = 0.0
        self.io[N], self.io[JAWS], self.io[SWEEPS] = n, problem.jaws, self.max_sweeps
        self.io[TOL2] = (self.tolerance * (1.0 + np.linalg.norm(problem.q))) ** 2
        self.impulse0 = problem.J.T @ problem.lam if n else np.zeros(3 * problem.jaws)
        self.problem = problem

    def warm(self) -> None:
        """Compile (or load from the cache) and replay once, on a one-contact problem."""
        saved = self.Wt[:3, :3].copy(), self.io.copy()
        self.Wt[:3, :3] = np.eye(3)
        self.io[:] = 0.0
        self.io[N], self.io[JAWS], self.io[SWEEPS] = 1, 1, 1
        RESOLVE(self.Wt, self.q, self.J, self.mu, self.r, self.u, self.io)
        RESOLVE(self.Wt, self.q, self.J, self.mu, self.r, self.u, self.io)
        self.Wt[:3, :3], self.io[:] = saved

    def solve(self, position, orientation, jaw: float) -> HapticForce:
        """The force for the device at this pose (between the loaded step and the next)."""
        p = self.problem
        targets = p.targets(position, orientation, jaw)
        moved = p.follow[:, None] * (targets - p.target)              # g Δ per jaw
        if p.n:
            self.io[DX:DX + 3 * p.jaws] = moved.ravel()
            RESOLVE(self.Wt, self.q, self.J, self.mu, self.r, self.u, self.io)
            impulse = self.io[OUT_IMPULSE:OUT_IMPULSE + 3 * p.jaws] / self.scale
            sweeps, residual = int(self.io[OUT_SWEEPS]), float(np.sqrt(self.io[OUT_ERROR2]))
        else:
            impulse, sweeps, residual = np.zeros(3 * p.jaws), 0, 0.0
        impulse = impulse.reshape(-1, 3)
        x = p.x + moved + p.compliance[:, None] * (impulse - self.impulse0.reshape(-1, 3))
        springs = p.stiffness[:, None] * (x - targets)
        return HapticForce.of_springs(springs, p.axis @ np.asarray(orientation).T, contact=impulse.sum(axis=0) / p.h,
                                      jaws=x, sweeps=sweeps, residual=residual, correction=np.zeros_like(springs))
