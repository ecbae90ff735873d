"""The discrete 3-D frictional contact problem (FCLib form): projected block Gauss-Seidel, and the
dispatch to the other methods (`solve_frictional_contact`, `FrictionalContactSolver`).

Problem (Acary et al., FCLib): n contacts, per contact the order (normal, tangent1, tangent2);
given the Delassus matrix W (3n x 3n), the free velocity q (3n,) and friction coefficients mu (n,),
find reactions r with u = W r + q such that, for each contact,

    K_mu ∋ r ⊥ û ∈ K_mu*,   û = (u_n + mu |u_t|, u_t),   K_mu = {r_n >= 0, |r_t| <= mu r_n}

(De Saxcé's modified velocity; K_mu* = {mu |v_t| <= v_n} is the dual cone). Its three cases are
separation (r = 0, u_n >= 0), sticking (u = 0, r inside K_mu) and sliding (u_n = 0,
r_t = -mu r_n u_t / |u_t|). With mu = 0 it is the LCP 0 <= u_n ⊥ r_n >= 0, r_t = 0.

Error measure (used to stop and reported in `info.residual`): the natural map of FCLib / Siconos
`fc3d_compute_error` with rho = 1,

    residual = || r - P_{K_mu}(r - û) ||_2 / (1 + ||q||_2),

the norm over all 3n components; it is zero exactly at a solution. (Siconos divides by ||q||;
the 1 + keeps it defined for q = 0.)

Methods (each in its module; this one validates, uploads and dispatches):
  * "auto" (the contact stage's default): Gauss-Seidel over the whole problem while it makes
    progress (every AUTO_PHASE sweeps, AUTO_PHASE_LARGE from AUTO_LARGE contacts on and
    AUTO_PHASE_SMALL below AUTO_SMALL, at least halve the residual, at a rate that reaches the
    tolerance within AUTO_HORIZON sweeps, at most AUTO_SWEEPS of them (AUTO_SWEEPS_SMALL below
    AUTO_SMALL), one launch), then "newton" from where it stopped. Warm-started
    problems of a few hundred rows mostly end within the sweeps, at microseconds each; the rest
    (many strongly coupled contacts, often more rows than the dofs they move: the press plate's
    2,382-3,465 rows, where a sweep gains ~1 % of the residual) end in a few Newton steps
    (bench/contact_solvers.py).
  * "newton": semi-smooth Newton on the Alart–Curnier function (tissue.contact.newton), on the
    host (dense LU among the closing contacts), Gauss-Seidel sweeps its fallback.
  * "gauss_seidel" (the API's default): projected block Gauss-Seidel with Anderson acceleration
    (tissue.contact.gauss_seidel), all sweeps in one launch. With `reduce`, while at most
    REDUCE_FRACTION of the contacts are in play (pushed or touching), the sweeps run on W among
    those alone, formed densely (FrictionalContactSolver._gauss_seidel); it pays on problems that
    need many sweeps.
  * "jacobi": relaxed block Jacobi, parallel (tissue.contact.jacobi).
Every method is made of one contact's pieces (tissue.contact.cone: the cone projection, the
natural-map error, the exact 3×3 local solve).

W is held on the device dense (row-major), as 3x3 blocks in block-CSR (a large sparse W), or as
its factors W = scale Σ P Q Pᵀ (`FactoredDelassus`, the form compliance warping gives: the contact
stage never forms W, and a sweep reads the bodies' compliances on the touched nodes instead); see
tissue.contact.layouts. Reactions are accumulated in the backend's float type (with float32,
tolerances much below 1e-6 are out of reach).
"""


import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import taichi as ti

from .. import backend
from ..errors import TissueError
from . import gauss_seidel, jacobi, newton
from .cone import natural_map_error2, natural_map_residual, project_cone
from .delassus import FactoredDelassus
from .layouts import CSR, DELASSUS, DENSE, FACTORED, IN_PLAY_MAX, PROBLEM, play_length
from .storage import Storage

METHODS = ("gauss_seidel", "jacobi", "newton", "auto")
LAYOUTS = ("auto", "dense", "csr")
# A sparse W goes to block-CSR when it has at least this many rows and at most this fill.
CSR_MIN_ROWS, CSR_MAX_FILL = 600, 0.2
ANDERSON_WINDOW = 5       # Gauss-Seidel's Anderson acceleration: sweeps combined (0: plain sweeps)
REDUCE_FRACTION = 0.5     # reduce: Gauss-Seidel on the contacts in play while they are at most this fraction
AUTO_PHASE, AUTO_SWEEPS = 16, 64  # auto: Gauss-Seidel while each AUTO_PHASE sweeps halve the residual, at
                                  # a rate that reaches the tolerance within AUTO_HORIZON sweeps, at most
AUTO_HORIZON = 100                # AUTO_SWEEPS, then Newton (Anderson's sweeps gain fast late: most of
                                  # liver_press's problems that reach the tolerance within 65 sweeps are
                                  # 30-500× above it at sweep 32, and Newton's step costs tens of sweeps)
AUTO_LARGE, AUTO_PHASE_LARGE = 1000, 4  # ... phases of 4 sweeps from 1,000 contacts on, where a sweep
                                        # is costly (over the factors of the press plate's 1,155 contacts),
                                        # the rate's horizon AUTO_SWEEPS
AUTO_SMALL, AUTO_PHASE_SMALL, AUTO_SWEEPS_SMALL = 32, 64, 256   # ... and below 32 contacts phases of 64,
                                        # at most 256 sweeps (the rate's horizon): there a sweep costs a
                                        # small fraction of Newton's host step (the floor scene's 12 contacts:
                                        # 14 of 72 steps fell back; bench.contact_solvers), and
                                        # where 16 sweeps did not halve the residual, 72-223 reached the
                                        # tolerance


@dataclass
class ContactInfo:
    iterations: int      # sweeps (Gauss-Seidel) or parallel iterations (Jacobi) performed
    residual: float      # natural-map residual of the returned r (see module docstring)
    time_s: float        # wall time of solve() until r is back on the host (device synced); counts
                         # uploading q and r0 (and compiling, on a process's first call), not W's upload
    converged: bool      # residual <= tol
    method: str = "gauss_seidel"


def _finite(name, a):
    if not np.all(np.isfinite(a)):
        raise TissueError(f"{name}: contains non-finite entries (nan or inf)")


def _dofs(contacts):
    """The rows 3i, 3i + 1, 3i + 2 of each contact i."""
    return (3 * np.asarray(contacts)[:, None] + np.arange(3)).ravel()


def _diagonal_blocks(W, n, sparse: bool):
    if sparse:
        B = sp.bsr_matrix(W, blocksize=(3, 3))
        rows = np.repeat(np.arange(n), np.diff(B.indptr))
        on = B.indices == rows
        D = np.zeros((n, 3, 3))
        np.add.at(D, rows[on], B.data[on])
        return D
    # A view [i, a, b] = W[3i + a, 3i + b] (gathering them by fancy indexing cost several times more)
    return np.diagonal(W.reshape(n, 3, n, 3), axis1=0, axis2=2).transpose(2, 0, 1)


class FrictionalContactSolver:
    """W and mu validated and uploaded once; solve() may then run for many q (as the haptic loop
    re-solves with a new free velocity between two simulation steps); renew() makes it the solver
    of another problem (the contact stage keeps one solver a run, renewed every step)."""

    def __init__(self, W, mu, method: str = "gauss_seidel", layout: str = "auto", omega=None, check: bool = True,
                 anderson: int = ANDERSON_WINDOW, reduce: bool = False, storage: Storage | None = None):
        """anderson: Gauss-Seidel's Anderson window (0: plain sweeps; see the module docstring).
        reduce: Gauss-Seidel sweeps the contacts in play alone, W among them formed (see `_gauss_seidel`;
        method 'gauss_seidel' only).
        check=False skips the finiteness and positive-definiteness checks of W (O(n²) and a
        3×3 eigenproblem per contact), and the finiteness and sign checks of μ, q and r0: for a
        caller that builds the problem itself (the contact stage, which checks the reactions).
        storage: where the device arrays and their argpacks are kept (Storage(host=True)), for a
        caller that solves many problems (the contact stage, every step): a solve on kept
        arrays sets no argument again (its launch replays, tissue.launch). The arrays are this
        solver's until the next solver on the same storage is made. By default, a storage of
        its own."""
        if method not in METHODS:
            raise TissueError(f"method: unknown value {method!r}; expected one of {', '.join(METHODS)}")
        if layout not in LAYOUTS:
            raise TissueError(f"layout: unknown value {layout!r}; expected one of {', '.join(LAYOUTS)}")
        if int(anderson) != anderson or anderson < 0:
            raise TissueError(f"anderson: must be a non-negative integer, got {anderson!r}")
        self.method, self.check, self._layout, self._omega = method, check, layout, omega
        self.anderson = int(anderson) if method != "jacobi" else 0
        self.storage = Storage(host=True) if storage is None else storage
        self._room = 0                  # contacts the problem's kept arrays hold (see _upload)
        self._uploaded = (-1, None)     # n and W's (layout, dims, scale) as last uploaded
        self.renew(W, mu, reduce)

    def renew(self, W, mu, reduce: bool = False) -> "FrictionalContactSolver":
        """This solver (its method, layout, checks and storage) for the problem (W, μ), uploaded
        into the arrays it keeps, without the set-up of a new solver: the arrays are looked up
        and their argpacks checked only after a growth, the sizes written when the number of
        contacts changed. Returns the solver."""
        check = self.check
        factored = isinstance(W, FactoredDelassus)
        sparse = not factored and not isinstance(W, np.ndarray) and sp.issparse(W)     # (scipy's check, asked once)
        if factored:
            if check:
                for name in ("blocks", "Q", "diagonal"):
                    _finite(f"W.{name}", getattr(W, name))
        elif sparse:
            W = sp.csr_matrix(W, dtype=np.float64)
            _finite("W", W.data)
        else:
            W = np.asarray(W, dtype=np.float64)
            if W.ndim != 2:
                raise TissueError(f"W: must be a 2-D matrix, got shape {W.shape}")
            if check:
                _finite("W", W)
        if W.shape[0] != W.shape[1]:
            raise TissueError(f"W: must be square, got shape {W.shape}")
        if W.shape[0] % 3:
            raise TissueError(f"W: size must be 3 x (number of contacts), got {W.shape[0]}")
        n = W.shape[0] // 3
        mu = np.asarray(mu, dtype=np.float64)
        if mu.ndim == 0:
            mu = np.full(n, float(mu))
        if mu.shape != (n,):
            raise TissueError(f"mu: expected a scalar or shape ({n},) to match W {W.shape}, got {mu.shape}")
        if check:
            _finite("mu", mu)
        if check and np.any(mu < 0):
            raise TissueError(f"mu: negative friction coefficient at contact {int(np.argmax(mu < 0))}")
        D = W.diagonal if factored else _diagonal_blocks(W, n, sparse)
        if n and check:
            sym = 0.5 * (D + D.transpose(0, 2, 1))
            lo = np.linalg.eigvalsh(sym)[:, 0]
            bad = np.flatnonzero(lo <= 1e-14 * np.abs(sym).max(axis=(1, 2)))
            if len(bad):
                raise TissueError(f"W: diagonal 3x3 block of contact {bad[0]} is not positive definite"
                                  f" (smallest eigenvalue {lo[bad[0]]:.3g}; {len(bad)} such block(s))")
        self.n, self.W, self.mu, self._D_host = n, W, mu, D
        self._swept = False             # the sweeps' W among the contacts in play is this problem's
        self.reduce = bool(reduce) and self.method == "gauss_seidel"      # (auto sweeps the whole problem)
        layout = self._layout
        dense = layout == "dense" or (layout == "auto" and (
            not sparse or W.shape[0] < CSR_MIN_ROWS or W.nnz > CSR_MAX_FILL * W.shape[0] ** 2))
        self.layout = FACTORED if factored else (DENSE if dense else CSR)
        # Jacobi's starting relaxation factor (given, or estimated from the spectrum of D^-1 W).
        self.omega = float(self._omega) if self._omega is not None else (
            self._initial_omega(D) if self.method == "jacobi" else 1.0)
        if n:
            self._upload(D)
        return self

    @property
    def dense(self) -> bool:
        """W held as a dense matrix on the device."""
        return self.layout == DENSE

    def _initial_omega(self, D):
        """min(1, 1/lambda_max(D^-1 W)) by a few power iterations (they approach from below)."""
        if self.n == 0:
            return 1.0
        Dinv = np.linalg.inv(D)
        x = np.random.default_rng(0).standard_normal(3 * self.n)
        lam = 1.0
        for _ in range(30):
            y = np.einsum("iab,ib->ia", Dinv, (self.W @ x).reshape(-1, 3)).ravel()
            lam = np.linalg.norm(y) / np.linalg.norm(x)
            x = y / np.linalg.norm(y)
        return min(1.0, 1.0 / lam)

    def _upload(self, D):
        """W, μ and the problem's arrays into the storage's kept arrays, and the argpacks over them
        (kept with it: built again only after a growth). The problem's arrays hold `_room`
        contacts; within it, and while no other solver wrote the storage, the problem's sizes
        and W's scalars are written only when they changed (_uploaded)."""
        real = backend.current().real
        self._npr = np.float64 if real == ti.f64 else np.float32
        st, n, m, window = self.storage, self.n, 3 * self.n, self.anderson
        if not st.claim(self):
            self._room, self._uploaded = 0, (-1, None)
        size, kept_W = self._uploaded
        if n > self._room:
            q = st.get("q", m, real)
            room = self._room = q.shape[0] // 3
            hist, gram, carried = gauss_seidel.history_shape(window, q.shape[0])   # room for as many rows as q
            P = dict(q=q, mu=st.get("mu", room, real), r=st.get("r", 3 * room, real), u=st.get("u", 3 * room, real),
                     hist=st.get("hist", hist[0], real, hist[1:]), gram=st.get("gram", gram[0], real, gram[1:]),
                     carried=st.get("carried", carried, ti.i32), stats=st.get("stats", 3, real),
                     sizes=st.get("sizes", 5, ti.i32), reals=st.get("reals", 1, real))
            self._P = st.pack("problem", PROBLEM, **P)
            self._q, self._r, self._u = P["q"], P["r"], P["u"]
            size = None
        st.put("mu", self.mu, real)
        if n != size:
            st.put("sizes", np.array([n, window, 0, 0, 0]), ti.i32)
        # W in its layout (see tissue.contact.layouts), the factored layout's y and z and its
        # scratch for W among the contacts in play (one element elsewhere), its sizes and its scale.
        none = st.get("none", 1, real)
        y = z = dense = none
        active = st.get("none_int", 1, ti.i32)
        dims, scale = [0, 0, 0], 1.0
        if self.layout == DENSE:
            W = self.W if isinstance(self.W, np.ndarray) else self.W.toarray()
            kept = st.get("W", m * m, real)
            if not (st.host and W.flags.c_contiguous and W.dtype == kept.dtype      # written in place: dense_buffer
                    and W.__array_interface__["data"][0] == kept.__array_interface__["data"][0]):
                kept = st.put("W", np.ravel(W), real)
            abc = (kept, none, none)
        elif self.layout == CSR:
            B = sp.bsr_matrix(sp.csr_matrix(self.W), blocksize=(3, 3))   # csr_matrix drops zeros
            B.sort_indices()
            abc = (st.put("indptr", B.indptr, ti.i32), st.put("indices", B.indices, ti.i32),
                   st.put("blocks", B.data, real, (3, 3)))
        else:
            W = self.W
            abc = (st.put("index", W.packed(), ti.i32), st.put("blocks", W.blocks, real, (3, 3)), st.put("Q", W.Q, real))
            dofs = max(1, int(W.y_offset[-1]))
            y, z = (st.get(name, dofs, real) for name in ("y", "z"))
            room = min(n, IN_PLAY_MAX)
            active = st.get("active", play_length(n, room), ti.i32)
            dense = st.get("dense", 9 * room * room + 3 * dofs, real)
            dims, scale = [len(W.blocks), len(W.y_offset) - 1, room], float(W.scale)
        if (self.layout, dims, scale) != kept_W:
            st.put("dims", np.array(dims), ti.i32)
            st.put("scale", np.array([scale]), real)
        self._W = st.pack(f"delassus {self.layout}", DELASSUS, a=abc[0], b=abc[1], c=abc[2],
                          Wd=st.put("Wd", D, real, (3, 3)), y=y, z=z, active=active, dense=dense,
                          dims=st.get("dims", 3, ti.i32),
                          scale=st.get("scale", 1, real))
        self._uploaded = (n, (self.layout, dims, scale))

    def _read(self, array) -> np.ndarray:
        """The problem's first 3n entries of one of its arrays (r, u), in float64."""
        m = 3 * self.n
        if isinstance(array, np.ndarray):
            return np.array(array[:m], dtype=np.float64)
        return array.to_numpy()[:m].astype(np.float64)

    def _write(self, array, values: np.ndarray) -> None:
        """values (3n,) into the problem's array `array` (q, r, u)."""
        if isinstance(array, np.ndarray):
            array[:len(values)] = values
        else:
            padded = np.zeros(array.shape, self._npr)
            padded[:len(values)] = values
            array.from_numpy(padded)

    def solve(self, q, tol: float = 1e-6, max_iterations: int = 1000, r0=None):
        n = self.n
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (3 * n,):
            raise TissueError(f"q: expected shape ({3 * n},) to match W {self.W.shape}, got {q.shape}")
        if self.check:
            _finite("q", q)
        if r0 is None:
            r0 = np.zeros(3 * n)
        r0 = np.asarray(r0, dtype=np.float64)
        if r0.shape != (3 * n,):
            raise TissueError(f"r0: expected shape ({3 * n},) to match W {self.W.shape}, got {r0.shape}")
        if self.check:
            _finite("r0", r0)
        if not (math.isfinite(tol) and tol > 0):
            raise TissueError(f"tol: must be a positive number, got {tol!r}")
        if int(max_iterations) != max_iterations or max_iterations < 0:
            raise TissueError(f"max_iterations: must be a non-negative integer, got {max_iterations!r}")
        max_iterations = int(max_iterations)
        if n == 0:
            self.u = np.zeros(0)
            return np.zeros(0), ContactInfo(0, 0.0, 0.0, True, self.method)

        t0 = time.perf_counter()
        self._q_host = q
        self._write(self._q, q)
        # Start inside the cones: Jacobi's relaxation keeps r where it starts.
        self._write(self._r, project_cone(r0.reshape(-1, 3), self.mu).ravel())
        q_norm = math.sqrt(q.dot(q))                  # (np.linalg.norm's formula, without its checks)
        tol_abs = tol * (1.0 + q_norm)
        iterations = getattr(self, f"_{self.method}")(max_iterations, tol_abs)
        backend.sync()
        r = self._read(self._r)
        elapsed = time.perf_counter() - t0
        if self.method != "jacobi" and self._npr == np.float64:
            # The kernel's own error and u of the returned r (the same formulas, in float64).
            residual = float(np.sqrt(self._last_error2)) / (1.0 + q_norm)
            self.u = self._read(self._u)
        else:
            residual = natural_map_residual(self.W, q, self.mu, r)   # in float64, whatever the backend
            self.u = self.W @ r + q
        info = ContactInfo(iterations, residual, elapsed, residual <= tol, self.method)
        return r, info

    def _sweeps(self, max_iterations, tol_abs, stall: int = 0, horizon: int | None = None) -> int:
        """Gauss-Seidel sweeps over the whole problem from the current r, in one launch (see
        gauss_seidel.run); sets self._last_error2 and self._stalled."""
        its, self._last_error2, self._stalled = gauss_seidel.run(self.layout, self._W, self._P, max_iterations,
                                                                 tol_abs, stall, horizon)
        self._swept = True
        return its

    def _formed_block(self, rows, cols) -> np.ndarray | None:
        """W between contacts `rows` and `cols` (ids) from W among the contacts in play that this
        problem's last sweeps formed (FACTORED, on the host; see gauss_seidel), when it holds
        them all; else None."""
        if not (self.layout == FACTORED and self._swept and self.storage.host):
            return None
        room = min(self.n, IN_PLAY_MAX)
        slot = self.storage.get("active", play_length(self.n, room), ti.i32)[:self.n]
        a, b = slot[rows], slot[cols]
        if room == 0 or (a < 0).any() or (b < 0).any():
            return None
        dense = self.storage.get("dense", 9 * room * room, self._npr)[:9 * room * room].reshape(3 * room, 3 * room)
        return dense[_dofs(a)][:, _dofs(b)]

    def _gauss_seidel(self, max_iterations, tol_abs):
        """Without `reduce`: sweeps over the whole problem, in one launch. With it: sweeps on the
        contacts in play, those pushed (r ≠ 0) or touching (u_n ≤ 0). Within an alarm distance
        most contacts never touch (the pressed liver: ~15 of ~150), so W among the k in play is
        formed (3k × 3k, dense) and swept: a sweep there costs a fraction of one over the
        factors, whose updates run through every dof the contacts move, and Anderson's
        combinations see only the reactions that move. Forming W there and checking the whole
        problem (numpy: a launch with the kernel's arguments costs more) cost a fixed
        price per solve, which pays on problems that need more than a few dozen sweeps (the liver
        pressed at 450 rows, side by side in one run: docs/performance.md, "Contact"). After each
        solve on the contacts in play, the whole problem's residual adds those found
        penetrating; separated ones carry r = 0, their exact solution, so the stopping rule is
        the whole problem's. Sweeps (the iteration cap) count those of every solve. When more
        than REDUCE_FRACTION of the contacts are in play, or nothing new comes in, the remaining
        sweeps run on the whole problem."""
        if not self.reduce:
            return self._sweeps(max_iterations, tol_abs)
        q = self._q_host
        r = self._read(self._r)
        its, play = 0, np.zeros(self.n, bool)
        while True:
            u = self.W @ r + q
            error2 = natural_map_error2(r, u, self.mu)
            if error2 <= tol_abs ** 2 or its >= max_iterations:
                break
            new = ((r.reshape(-1, 3) != 0).any(axis=1) | (u[0::3] <= 0)) & ~play
            if not new.any() or np.count_nonzero(play | new) > REDUCE_FRACTION * self.n:
                self._write(self._r, r)
                return its + self._sweeps(max_iterations - its, tol_abs)
            play |= new
            idx = np.flatnonzero(play)
            dofs = _dofs(idx)
            sub = FrictionalContactSolver(self._block(idx, idx), self.mu[idx], layout="dense", check=False,
                                          anderson=self.anderson, reduce=False, storage=self._in_play())
            r_play, info = sub.solve(q[dofs], tol_abs / (1.0 + np.linalg.norm(q[dofs])), max_iterations - its,
                                     r[dofs])
            its += info.iterations
            r = np.zeros(3 * self.n)
            r[dofs] = r_play
        self._write(self._r, r)
        self._write(self._u, u)
        self._last_error2 = error2
        return its

    def _in_play(self) -> Storage:
        """The storage of `reduce`'s solvers on the contacts in play (kept in this one's)."""
        return self.storage.child("in play")

    def _auto(self, max_iterations, tol_abs):
        """Gauss-Seidel over the whole problem (most warm-started problems end within a few dozen
        sweeps, at a few µs a sweep) while every AUTO_PHASE sweeps (AUTO_PHASE_LARGE on large
        problems, where sweeps cost more than Newton's first steps; AUTO_PHASE_SMALL on small ones,
        where they cost far less) at least halve the residual, at a rate that reaches the tolerance
        within AUTO_HORIZON sweeps (AUTO_SWEEPS on large problems, AUTO_SWEEPS_SMALL on small
        ones), at most AUTO_SWEEPS (AUTO_SWEEPS_SMALL), in one launch; then Newton from where it
        stopped (the problems whose sweeps crawl: many coupled contacts, W ill-conditioned or
        singular)."""
        cap = min(AUTO_SWEEPS, max_iterations)
        if self.n < AUTO_SMALL:
            cap = min(AUTO_SWEEPS_SMALL, max_iterations)
            its = self._sweeps(cap, tol_abs, AUTO_PHASE_SMALL, cap)
        elif self.n < AUTO_LARGE:
            its = self._sweeps(cap, tol_abs, AUTO_PHASE, min(AUTO_HORIZON, max_iterations))
        else:
            its = self._sweeps(cap, tol_abs, AUTO_PHASE_LARGE)
        if self._last_error2 <= tol_abs ** 2 or its >= max_iterations:
            return its
        return its + self._newton(max_iterations - its, tol_abs)

    def _newton(self, max_iterations, tol_abs):
        """Semi-smooth Newton (tissue.contact.newton) from the current r, on the host; Gauss-Seidel
        sweeps (this solver's kernel, with Anderson) are its fallback when a line search fails."""
        def fallback(r, sweeps):
            self._write(self._r, r)
            done = self._sweeps(sweeps, tol_abs) if sweeps else 0
            return self._read(self._r), done

        # A factored W stays factored: Newton reads W among the closing contacts once per solve
        # (newton._Shared) and products through the factors.
        r, u, its, err2 = newton.solve(self.W, self._block, self._q_host, self.mu, self._D_host,
                                       self._read(self._r), tol_abs, max_iterations, fallback,
                                       lambda r, u: natural_map_error2(r, u, self.mu))
        self._write(self._r, r)
        self._write(self._u, u)
        self._last_error2 = err2
        return its

    def _block(self, rows, cols) -> np.ndarray:
        """W between contacts `rows` and `cols` (ids), dense (FACTORED: read from W among the
        contacts in play where the sweeps formed it, else from the factors)."""
        if self.layout == FACTORED:
            formed = self._formed_block(rows, cols)
            return formed if formed is not None else self.W.block(rows, cols)
        r, c = _dofs(rows), _dofs(cols)
        if sp.issparse(self.W):                     # (also a small sparse W held densely)
            return self.W[r][:, c].toarray()
        return self.W[np.ix_(r, c)]

    def _jacobi(self, max_iterations, tol_abs):
        its, self.last_omega = jacobi.solve(self.layout, self._W, self._P, self.omega, max_iterations, tol_abs)
        return its


def dense_buffer(storage: Storage, m: int) -> np.ndarray:
    """An (m, m) float64 array for W: on the CPU in float64, the memory where a solver on `storage`
    keeps a dense W, so that what the caller writes there is read in place (no copy); elsewhere a
    new array."""
    if storage.host and backend.current().real == ti.f64:
        return np.asarray(storage.get("W", m * m, ti.f64)[:m * m]).reshape(m, m)
    return np.empty((m, m))


def solve_frictional_contact(W, q, mu, tol: float = 1e-6, max_iterations: int = 1000, r0=None,
                             method: str = "gauss_seidel", layout: str = "auto", anderson: int = ANDERSON_WINDOW,
                             reduce: bool = False):
    """Solve the frictional contact problem (W, q, mu); returns (r, ContactInfo).

    W: (3n, 3n) Delassus matrix, dense or scipy sparse; q: (3n,) free velocity; mu: scalar or (n,);
    per contact the order is (normal, tangent1, tangent2). Stops when the natural-map residual
    ||r - P_K(r - û)|| / (1 + ||q||) is <= tol or after max_iterations sweeps; r0 warm-starts.
    method: "gauss_seidel" (serial sweeps), "jacobi" (parallel, slower convergence), "newton"
    (semi-smooth Newton, for many coupled contacts) or "auto" (Gauss-Seidel, then Newton if the
    sweeps stall; the contact stage's default).
    layout: "auto" | "dense" | "csr" storage of W on the device (auto: block-CSR for a large sparse W).
    anderson: Gauss-Seidel's Anderson acceleration window (0: plain projected sweeps).
    reduce: method "gauss_seidel" on the contacts in play (pushed or touching) alone, W among them formed:
    faster when most contacts are apart and many sweeps are needed.
    Taichi must be initialised (tissue.backend.init). Bad input raises TissueError.
    """
    return FrictionalContactSolver(W, mu, method, layout, anderson=anderson, reduce=reduce).solve(
        q, tol, max_iterations, r0)
