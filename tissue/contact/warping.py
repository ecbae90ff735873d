"""Compliance warping (paper §3.2, §3.5): W = h H A⁻¹ Hᵀ and the corrective motion of
tissue.contact.compliance (its derivation and conventions), with A⁻¹ approximated by the rest
compliance turned by the nodal rotations, so that nothing is factorised per step.

Warping. A = R A₀ Rᵀ would hold exactly if every element turned by the same R (A₀: the rest
matrix, R block-diagonal); with nodal rotations Rᵥ (the polar factor of the sum of the incident
elements' rotations, i.e. their orthonormalised average) it is the paper's approximation:

    W ≈ h (H R) A₀⁻¹ (H R)ᵀ,     x⁺ ≈ x_free + R h A₀⁻¹ (H R)ᵀ λ.

For a free body (no fixed node) only the deforming part is warped: A₀⁻¹ = Q + T Tᵀ / (c m) (T the
uniform translations, c = 1 + h α_M, m the mass), and the translation, which rotating cannot
change for a rigid turn but bends when nodal rotations differ, is applied as it is:

    W ≈ h ((H R) Q (H R)ᵀ + (H T)(H T)ᵀ / (c m)),   x⁺ ≈ x_free + h (R Q (H R)ᵀ λ + T (H T)ᵀ λ / (c m)),

so the total impulse moves the centre of mass exactly as the unwarped operator would.

A₀⁻¹ is computed once, dense, from the assembled sparse A₀ (tissue.solver.reference) with the
body's dt, damping and fixed nodes (their rows and columns are zero: fixed nodes do not move). The
same approximate operator builds W and applies the correction, so δ = δ_free + W λ holds exactly
for what is applied; the approximation only changes which λ is found.

Kernels (one launch per body for W, one for the correction). H is stored in JDS of 3×3 blocks
(a contact's three rows touch the same nodes; constraints.py), and only the t nodes the rows
touch matter: (1) Hr = H R, a 3×3 block per stored block; U = A₀⁻¹ Hrᵀ restricted to the 3t
touched dofs, an entry (block row, dof) per thread; (2) W += h Hr U, a 3×3 block of W per thread,
upper triangle mirrored. For the liver pressed by the probe (about 120 block rows on 50 nodes of
373) that is about 0.4 M multiply-adds each for U and W (U through all 3n dofs: 2.5 M). The
correction gathers r₀ = Hrᵀ λ on the touched dofs (serially: a fixed summation order) and then
reads the touched rows of A₀⁻¹: dx = R h A₀⁻¹ r₀, a thread per node. The nodal
rotations come in the same launch as W (Newton–Schulz from the elements' mean rotation, the
FEM's polar iteration where that is far from orthogonal). On the CPU, bodies of this size run
every loop on one thread: the thread pool's dispatch costs more than it saves on 2 cores.
"""

import hashlib

import numpy as np
import taichi as ti

from .. import backend
from ..errors import TissueError
from ..fem.corotational import element_rotation
from ..fem.model import MODEL
from ..fem.rotations import nodal_rotation
from ..launch import kept_pack, replayed
from ..mesh import cache
from ..solver.reference import rest_compliance
from .constraints import JaggedDiagonal
from .storage import Storage

SERIAL_BELOW_NODES = 10_000    # nodes: below, the CPU runs the compliance loops on one thread



@ti.kernel
def _nodal_rotations(Re: ti.types.ndarray(), valence: ti.types.ndarray(), incidence: ti.types.ndarray(),
                     out: ti.types.ndarray(), tol: float):
    for v in range(out.shape[0]):
        out[v] = nodal_rotation(Re, valence, incidence, v, tol)


@ti.kernel
def _polar_rotations(m: MODEL, x: ti.types.ndarray(), v: ti.types.ndarray(), h: ti.f64, start: ti.types.ndarray(),
                     out: ti.types.ndarray(), tol: ti.f64, serial: ti.template()):
    """The polar rotation of each element at the free motion's start, x − h v (where it linearised,
    as a "polar" body's own rotations are), for bodies whose own rotations are not polar ("large":
    see WarpedCompliance)."""
    ti.loop_config(serialize=serial)
    for n in range(m.counts[0]):
        start[n] = x[n] - h * v[n]
    ti.loop_config(serialize=serial)
    for e in range(m.counts[1]):
        out[e] = element_rotation(m, e, start, "polar", tol)


# A launch's arrays, in one flat argpack (tissue.solver.step_kernels says why flat): the nodal
# rotations R, A₀⁻¹ (C0), the touched nodes' blocks of rows in C0 (rows), Hr, the JDS (jds:
# JaggedDiagonal.packed; value) and the step's scalars in two small arrays, `sizes` (SIZES) and
# `reals` (REALS); for the rotations and W (WARP), the FEM's element rotations and gather index and
# the scratch U, ht, Qt; for the correction (CORRECTION), λ, its scratch r0 and pushed, and the
# solver's x and v. Each holds only what its kernels read: the launcher costs per ndarray, even
# replayed. Every member is an array kept between steps, so the launch is replayed
# (tissue.launch) whatever the step's sizes.
SHARED_MEMBERS = ("R", "C0", "rows", "hr", "jds", "value", "sizes", "reals")
WARP = ti.types.argpack(**{name: ti.types.ndarray() for name in (*SHARED_MEMBERS, "Re", "valence", "incidence",
                                                                 "U", "ht", "Qt", "before")})
CORRECTION = ti.types.argpack(**{name: ti.types.ndarray() for name in (*SHARED_MEMBERS, "lam", "r0", "pushed",
                                                                       "x", "v")})
WARP_SIZES = ("n_active", "k_max", "nnz", "n_touched", "q_offset", "pos_offset", "n_rows", "gather", "q_before",
              "ld_before", "n_rotated")
WARP_REALS = ("h", "inverse_mass", "tolerance")
N_ACTIVE, K_MAX, NNZ, N_TOUCHED, Q_OFFSET, POS_OFFSET, N_ROWS, GATHER, Q_BEFORE, LD_BEFORE, N_ROTATED = \
    range(len(WARP_SIZES))
H, INVERSE_MASS, TOLERANCE = range(len(WARP_REALS))


@ti.func
def _jds_offsets(n_active, k_max, nnz):
    """Offsets of perm, count, jd_ptr, node, local, touched in JaggedDiagonal.packed."""
    o_count = n_active
    o_ptr = 2 * n_active
    o_node = o_ptr + k_max + 1
    o_local = o_node + nnz
    return o_count, o_ptr, o_node, o_local, o_local + nnz


@ti.func
def _row_translation(k: ti.template(), o_count, o_ptr, i):
    """(H T)ᵢ: the sum of block row i's blocks, its (unrotated) response to a uniform translation."""
    G = ti.Matrix.zero(float, 3, 3)
    for l in range(k.jds[o_count + i]):
        e = k.jds[o_ptr + l] + i
        G += k.value[e]
    return G


@ti.func
def _rotations_and_hr(k: ti.template(), o_node, nnz, serial: ti.template()):
    """The nodal rotations of the first sizes[N_ROTATED] nodes (every node, the correction reading
    them; none where R is the solver's: see WarpedCompliance.prepare) and kernel 1, Hr = H R (a 3×3
    block per JDS entry)."""
    tol = k.reals[TOLERANCE]
    ti.loop_config(serialize=serial)
    for v in range(k.sizes[N_ROTATED]):
        k.R[v] = nodal_rotation(k.Re, k.valence, k.incidence, v, tol)
    ti.loop_config(serialize=serial)
    for e in range(nnz):
        k.hr[e] = k.value[e] @ k.R[k.jds[o_node + e]]


@ti.func
def _translations_and_gather(k: ti.template(), Qt: ti.template(), q0, Qb: ti.template(), ld, gather,
                             serial: ti.template()):
    """The rows' translations H T, and with gather (1; 0: Qt holds it already) Q among the d = 3
    sizes[N_TOUCHED] touched dofs gathered once into Qt from q0 (ld × ld, row-major; a free body's
    factor, ld = d + 3, adds the translation's block): a compact copy stays in cache where scattered reads of the whole Q (3n ×
    3n, 10 MB for the liver) miss it. With sizes[LD_BEFORE] > 0, Qb from sizes[Q_BEFORE] holds last
    step's gather (that row length), and `before` each touched node's index among its nodes (-1:
    new): the entries between nodes touched both times are copied from there (the same numbers, in
    cache: the touched nodes change a few at a time), only the others read from the whole Q."""
    n_active, inverse_mass = k.sizes[N_ACTIVE], k.reals[INVERSE_MASS]
    o_count, o_ptr, _, _, o_touched = _jds_offsets(n_active, k.sizes[K_MAX], k.sizes[NNZ])
    ti.loop_config(serialize=serial)
    for i in range(n_active):
        k.ht[i] = _row_translation(k, o_count, o_ptr, i)
    # By 3×3 node blocks: a node's index, its `before` and its row of C0 read once a block, not
    # once an entry. One thread: nested loops (a top-level ti.ndrange divides for its two indices
    # at every entry); else one parallel loop over all the blocks.
    nt, blocks = k.sizes[N_TOUCHED], ld // 3
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for a in range(blocks * gather):
            for m in range(blocks):
                _gather_block(k, Qt, q0, Qb, a, m, ld, nt, o_touched, inverse_mass)
    else:
        for a, m in ti.ndrange(blocks * gather, blocks):
            _gather_block(k, Qt, q0, Qb, a, m, ld, nt, o_touched, inverse_mass)


@ti.func
def _gather_block(k: ti.template(), Qt: ti.template(), q0, Qb: ti.template(), a, m, ld, nt, o_touched,
                  inverse_mass):
    """Node block (a, m) of the gathered Q (see _translations_and_gather) into Qt: last step's
    gather where both nodes were touched then, else read from the whole Q; the translation's block
    past the nt touched nodes."""
    qb0, ldb = k.sizes[Q_BEFORE], k.sizes[LD_BEFORE]
    at = q0 + 3 * a * ld + 3 * m
    if a < nt and m < nt:
        pa, pm = -1, -1
        if ldb > 0:
            pa, pm = k.before[a], k.before[m]
        if pa >= 0 and pm >= 0:
            kept = qb0 + 3 * pa * ldb + 3 * pm
            for p, q in ti.static(ti.ndrange(3, 3)):
                Qt[at + p * ld + q] = Qb[kept + p * ldb + q]
        else:
            row, col = 3 * k.rows[a], 3 * k.jds[o_touched + m]
            for p, q in ti.static(ti.ndrange(3, 3)):
                Qt[at + p * ld + q] = k.C0[row + p, col + q]
    else:
        for p, q in ti.static(ti.ndrange(3, 3)):
            Qt[at + p * ld + q] = inverse_mass if a == m and p == q else 0.0


# One launch each (parallel loops; on one thread for small bodies on the CPU): _rotate for the
# correction alone, _assemble to form W, _factor for W's factors.

@ti.kernel
def _rotate(k: WARP, serial: ti.template()):
    """The nodal rotations and Hr, what the correction needs when W was neither formed nor factored."""
    n_active, nnz = k.sizes[N_ACTIVE], k.sizes[NNZ]
    o_count, o_ptr, o_node, o_local, o_touched = _jds_offsets(n_active, k.sizes[K_MAX], nnz)
    _rotations_and_hr(k, o_node, nnz, serial)


@ti.kernel
def _assemble(k: WARP, W: ti.types.ndarray(), serial: ti.template()):
    """The nodal rotations and Hr; H T and Q among the touched dofs (Qt); U = Q Hrᵀ there; and
    kernel 2: W += h (Hr U + (H T)(H T)ᵀ / (c m)), W (n_rows × n_rows) row-major in the flat W."""
    n_active, nnz, n = k.sizes[N_ACTIVE], k.sizes[NNZ], k.sizes[N_ROWS]
    h, inverse_mass = k.reals[H], k.reals[INVERSE_MASS]
    o_count, o_ptr, o_node, o_local, o_touched = _jds_offsets(n_active, k.sizes[K_MAX], nnz)
    _rotations_and_hr(k, o_node, nnz, serial)
    d = 3 * k.sizes[N_TOUCHED]
    _translations_and_gather(k, k.Qt, 0, k.Qt, d, k.sizes[GATHER], serial)
    # U(block row i, touched dof m) (3 rows) = Σ_blocks Hr(i, block) Q(block's dofs, m); m runs
    # fastest, so neighbouring threads read neighbouring entries of a row.
    ti.loop_config(serialize=serial)
    for i, m in ti.ndrange(n_active, d):
        s = ti.Vector([0.0, 0.0, 0.0])
        for l in range(k.jds[o_count + i]):
            e = k.jds[o_ptr + l] + i
            b = 3 * k.jds[o_local + e] * d + m
            s += k.hr[e] @ ti.Vector([k.Qt[b], k.Qt[b + d], k.Qt[b + 2 * d]])
        k.U[i * d + m] = s
    # Kernel 2: the 3×3 block (i, j) of W is h U(i, j's dofs) Hr(j, ·)ᵀ; upper triangle, mirrored.
    ti.loop_config(serialize=serial)
    for i, j in ti.ndrange(n_active, n_active):
        if j >= i:
            B = ti.Matrix.zero(float, 3, 3)
            for l in range(k.jds[o_count + j]):
                e = k.jds[o_ptr + l] + j
                a = i * d + 3 * k.jds[o_local + e]
                B += ti.Matrix.cols([k.U[a], k.U[a + 1], k.U[a + 2]]) @ k.hr[e].transpose()
            if inverse_mass != 0.0:
                B += inverse_mass * k.ht[i] @ k.ht[j].transpose()
            ri, rj = 3 * k.jds[i], 3 * k.jds[j]
            for p, q in ti.static(ti.ndrange(3, 3)):
                W[(ri + p) * n + rj + q] = W[(ri + p) * n + rj + q] + h * B[p, q]
            if i != j:
                for p, q in ti.static(ti.ndrange(3, 3)):
                    W[(rj + q) * n + ri + p] = W[(rj + q) * n + ri + p] + h * B[p, q]


@ti.kernel
def _factor(k: WARP, P: ti.types.ndarray(), Q: ti.types.ndarray(), Qb: ti.types.ndarray(), diagonal: ti.types.ndarray(),
            pos: ti.types.ndarray(), serial: ti.template()):
    """The factors of W (tissue.contact.FactoredDelassus): Hr and H T into P at this body's
    entries of `pos` (from pos_offset), Q among the touched dofs into Q from q_offset (with the
    translation's block for a free body; from last step's factor Qb where it has them: see
    _translations_and_gather), and W's diagonal blocks:
    diagonal[block row] += h (Hr Q Hrᵀ + (H T)(H T)ᵀ / (c m))."""
    n_active, nnz = k.sizes[N_ACTIVE], k.sizes[NNZ]
    q0, p0 = k.sizes[Q_OFFSET], k.sizes[POS_OFFSET]
    h, inverse_mass = k.reals[H], k.reals[INVERSE_MASS]
    o_count, o_ptr, o_node, o_local, o_touched = _jds_offsets(n_active, k.sizes[K_MAX], nnz)
    _rotations_and_hr(k, o_node, nnz, serial)
    d = 3 * k.sizes[N_TOUCHED]
    ld = d + (3 if inverse_mass != 0.0 else 0)      # Q's row length
    _translations_and_gather(k, Q, q0, Qb, ld, 1, serial)
    ti.loop_config(serialize=serial)
    for i in range(n_active):
        count = k.jds[o_count + i]
        B = ti.Matrix.zero(float, 3, 3)
        for l in range(count):
            e = k.jds[o_ptr + l] + i
            for c in ti.static(ti.ndrange(3, 3)):
                P[pos[p0 + e], c[0], c[1]] = k.hr[e][c[0], c[1]]
            a = 3 * k.jds[o_local + e]
            for l2 in range(count):
                f = k.jds[o_ptr + l2] + i
                b = 3 * k.jds[o_local + f]
                Qab = ti.Matrix.zero(float, 3, 3)
                for p, q in ti.static(ti.ndrange(3, 3)):
                    Qab[p, q] = Q[q0 + (a + p) * ld + b + q]
                B += k.hr[e] @ Qab @ k.hr[f].transpose()
        if inverse_mass != 0.0:
            for c in ti.static(ti.ndrange(3, 3)):
                P[pos[p0 + nnz + i], c[0], c[1]] = k.ht[i][c[0], c[1]]
            B += inverse_mass * k.ht[i] @ k.ht[i].transpose()
        row = k.jds[i]
        for p, q in ti.static(ti.ndrange(3, 3)):
            diagonal[row, p, q] = diagonal[row, p, q] + h * B[p, q]


@ti.kernel
def _correct(k: CORRECTION, serial: ti.template()):
    """r₀ = (H R)ᵀ λ on the touched dofs and the total impulse p = (H T)ᵀ λ (serial: a fixed
    summation order; p in r₀'s last slot), then per node dx = h (R Q r₀ + p / (c m)) (a gather over
    the touched columns with r₀ ≠ 0, listed in `pushed`), x += dx, v += dx / h."""
    n_active, nnz, n_touched = k.sizes[N_ACTIVE], k.sizes[NNZ], k.sizes[N_TOUCHED]
    h, inverse_mass = k.reals[H], k.reals[INVERSE_MASS]
    o_count, o_ptr, o_node, o_local, o_touched = _jds_offsets(n_active, k.sizes[K_MAX], nnz)
    last = k.r0.shape[0] - 1
    ti.loop_config(serialize=serial)
    for t in range(n_touched):
        k.r0[t] = ti.Vector([0.0, 0.0, 0.0])
    ti.loop_config(serialize=True)                  # a fixed summation order, no races
    for i in range(n_active):
        ri = 3 * k.jds[i]
        li = ti.Vector([k.lam[ri], k.lam[ri + 1], k.lam[ri + 2]])
        if i == 0:
            k.r0[last] = ti.Vector([0.0, 0.0, 0.0])
        k.r0[last] += _row_translation(k, o_count, o_ptr, i).transpose() @ li
        for l in range(k.jds[o_count + i]):
            e = k.jds[o_ptr + l] + i
            a = k.jds[o_local + e]
            k.r0[a] = k.r0[a] + k.hr[e].transpose() @ li
    # Most rows within the alarm distance carry no impulse (the pressed liver: ~140 of ~155
    # contacts): only the touched nodes pushed read their rows of A₀⁻¹, the costly part (cold in
    # cache: 3 rows of 3n per node).
    ti.loop_config(serialize=True)
    for _ in range(1):
        count = 0
        for t in range(n_touched):
            if k.r0[t].norm_sqr() > 0.0:
                k.pushed[count] = t
                count += 1
        k.pushed[k.pushed.shape[0] - 1] = count
    ti.loop_config(serialize=serial)
    for n in range(k.x.shape[0]):
        # A₀⁻¹ is symmetric: read its touched rows, where neighbouring nodes are neighbouring entries.
        s = ti.Vector([0.0, 0.0, 0.0])
        for a in range(k.pushed[k.pushed.shape[0] - 1]):
            t = k.pushed[a]
            row = 3 * k.rows[t]
            g = k.r0[t]
            for c in ti.static(range(3)):
                s[c] += k.C0[row, 3 * n + c] * g[0] + k.C0[row + 1, 3 * n + c] * g[1] + k.C0[row + 2, 3 * n + c] * g[2]
        dx = h * (k.R[n] @ s + inverse_mass * k.r0[last])
        k.x[n] = k.x[n] + dx
        k.v[n] = k.v[n] + dx / h


_rotate_replayed, _assemble_replayed, _factor_replayed, _correct_replayed = (
    replayed(kernel) for kernel in (_rotate, _assemble, _factor, _correct))


def _rest_compliance(solver) -> np.ndarray:
    """The body's dense A₀⁻¹ (reference.rest_compliance), kept in the on-disk cache
    (tissue.mesh.cache) under a hash of A₀ and the held nodes, what it is a function of: scenes
    that share a body at the same dt and damping (liver_press and liver_grasp) invert it once per
    machine. Reading it back costs a small part of inverting A₀."""
    A, fixed = solver.rest_matrix(), np.asarray(solver.fixed_nodes, dtype=np.int64)
    digest = hashlib.sha256(str((A.shape, A.data.dtype, A.indices.dtype)).encode())
    for array in (A.data, A.indices, A.indptr, fixed):
        digest.update(np.ascontiguousarray(array).tobytes())

    def invert():
        fem = solver.fem
        return {"C": rest_compliance(fem.mesh, fem.material, solver.dt, fixed=fixed, matrix=A)}

    return cache.cached_arrays(invert, ("C",), "rest_compliance", matrix=digest.hexdigest())["C"]


class WarpedCompliance:
    """One soft body's rest compliance A₀⁻¹ (dense, on the device) and nodal rotations.

    Per step: `prepare(jds)` takes the body's rows of H; `add_to(W)` computes, in one launch, the
    nodal rotations (unless the solver's multigrid computed them this step: see prepare), Hr = H R,
    U = A₀⁻¹ Hrᵀ restricted to the dofs the rows touch, and W += h Hr U; `correct(λ)` applies
    x += R h A₀⁻¹ Hrᵀ λ in one more launch.

    The nodal rotations average POLAR element rotations whatever the body's elasticity uses: for
    "large" (edge frames) they are computed where the free motion started, x − h v, in one more
    launch. An edge frame turns away from the polar rotation by about the element's shear, and a
    compliance warped by it is not R A₀⁻¹ Rᵀ of any rotated body: its correction added energy
    where the body was sheared (the cantilever resting or jerked onto the floor, docs/stability.md).
    """

    def __init__(self, solver):
        be = backend.current()
        self.solver, self.real = solver, be.real
        self._np = np.float64 if be.real == ti.f64 else np.float32
        # The element types of the per-step arrays (Taichi builds a type anew at each call: once here).
        self._mat3, self._vec3 = ti.types.matrix(3, 3, be.real), ti.types.vector(3, be.real)
        self.source = None                  # a CuttingCompliance to read A₀⁻¹ from (follow)
        self._tol = solver.fem.rotation_tolerance
        self._own_polar = solver.fem.rotation != "large"     # else its polar rotations: element_rotations
        self.storage = Storage()                              # this step's scratch: see prepare
        self._ready = False
        self._qt_rows = None                # the rows whose Q among their touched nodes Qt holds (add_to)
        self._kept_packs = {}               # the launches' argpacks by kind: see _pack
        # The step's scalars (see WARP), written in place each step.
        self._sizes, self._reals = np.zeros(len(WARP_SIZES), np.int32), np.zeros(len(WARP_REALS), self._np)
        self._before = self.storage.get("before", 1, ti.i32)   # see factor
        self.follow_edits()

    def follow_edits(self) -> None:
        """A₀⁻¹ and the per-node arrays for the body's current topology: read from the cutting
        compliance when following one, else inverted anew (dense: a fallback for edits made
        without one)."""
        solver = self.solver
        fem = solver.fem
        n = fem.n_nodes
        self.jds = None                  # the next rows are written anew (prepare)
        self._qt_rows = None             # and Q gathered anew from the new C0
        if self.source is not None:      # folded only where W needs it (prepare)
            self.source.update()
            self.C0, self.inverse_mass = self.source.C, 0.0
        else:
            C0 = _rest_compliance(solver)
            # A free body's rigid translation is not warped: A₀⁻¹ = Q + S with S = T Tᵀ / (c m) (T
            # the uniform translations, c = 1 + h α_M, m the mass; K T = 0, so A₀ T = c M T), and Q
            # moves no momentum (Tᵀ M Q = 0). Rotating S too by nodal rotations that differ from
            # node to node would bend the translation: the block on a slope slid 1.4 % too slowly
            # with "polar".
            free = len(solver.fixed_nodes) == 0
            self.inverse_mass = 1.0 / ((1.0 + solver.dt * solver.rayleigh_mass) * fem.model.mass.sum()) \
                if free else 0.0
            self.C0_host = 0.5 * (C0 + C0.T) - self.inverse_mass * np.kron(np.ones((n, n)), np.eye(3))   # Q
            # Ndarrays, not fields: the kernels take them as ndarray parameters, compiled once for
            # every body (a field per body would compile them again for each).
            self.C0 = ti.ndarray(self.real, self.C0_host.shape)
            self.C0.from_numpy(self.C0_host.astype(self._np))
        capacity = fem.model.node_capacity   # as the solver's state: a cut within it allocates nothing here
        if getattr(self, "_own_R", None) is None or self._own_R.shape[0] != capacity:
            self._own_R = ti.ndarray(ti.types.matrix(3, 3, self.real), capacity)
            self.r0 = ti.ndarray(ti.types.vector(3, self.real), capacity + 1)    # + the total impulse
            self.pushed = ti.ndarray(ti.i32, capacity + 1)                       # touched nodes with r₀ ≠ 0, + their count
        self.R = self._own_R                 # the nodal rotations the launches read (see prepare)
        # One thread on the CPU for bodies of the sizes W is used for (the thread pool's dispatch
        # costs more than it saves at a few hundred rows on 2 cores); parallel above.
        self.serial = backend.current().arch == "cpu" and n < SERIAL_BELOW_NODES

    def follow(self, compliance) -> None:
        """Read A₀⁻¹ from a tissue.cutting.CuttingCompliance of this body (the same rest matrix:
        its dt and damping must be the solver's), its lazy factors folded in a step whose rows
        touch the body. Its C is A₀⁻¹ whole, so
        a free body's translation is warped with the rest (the plain warping of the paper): after
        a cut, one body may be several pieces, each with a translation of its own."""
        solver = self.solver
        if compliance.model is not solver.model or \
                not np.isclose(compliance.mass_weight, 1.0 + solver.dt * solver.rayleigh_mass) or \
                not np.isclose(compliance.stiffness_weight, solver.dt * solver.rayleigh_stiffness + solver.dt ** 2):
            raise TissueError("contact: the cutting compliance followed must be of this body's model, at its "
                              "solver's dt and damping")
        self.source, self._version, self._gathered = compliance, -1, None
        self.follow_edits()

    def element_rotations(self):
        """The element rotations the warping averages: the FEM's own of the last free motion, or
        for "large" the polar ones where it started (one launch)."""
        solver = self.solver
        fem = solver.fem
        if self._own_polar:
            return fem.R
        model = fem.model
        start = self.storage.get("start", model.node_capacity, self._vec3)
        Re = self.storage.get("polar", model.element_capacity, self._mat3)
        _polar_rotations(model.pack, solver.x, solver.v, solver.dt, start, Re, self._tol, self.serial)
        return Re

    def update_rotations(self) -> None:
        """Nodal rotations from the element rotations (`element_rotations`; `add_to` also
        computes them, in its own launch)."""
        self.R = self._own_R
        _nodal_rotations(self.element_rotations(), *self.solver.fem.model.gather_index(), self.R, self._tol)

    def nodal_rotations(self) -> np.ndarray:
        return self.R.to_numpy()[:self.solver.fem.n_nodes].astype(np.float64)

    def prepare(self, jds: JaggedDiagonal) -> None:
        """This step's rows of H (the work is done by `add_to` or `factor`, or by `correct`
        without them), written into the arrays the launches keep; there already when they are
        last step's (the contact stage keeps the rows of contacts at rest)."""
        self._ready = False
        self._element_rotations = self.element_rotations()     # this step's, kept rows or not
        # The nodal rotations: the solver's, where its step computed them from these element
        # rotations at this tolerance (the multigrid's), else computed by this step's launch.
        shared = self.solver.nodal_rotations(self._tol) if self._own_polar else None
        self.R = self._own_R if shared is None else shared
        self._sizes[N_ROTATED] = self.R.shape[0] if shared is None else 0
        if jds is self.jds and self.source is None:
            return
        self.jds = jds
        real, storage = self.real, self.storage
        blocks = self._read_source(jds.touched) if self.source is not None else jds.touched
        self.rows = storage.put("rows", blocks, ti.i32)
        self._jds = storage.put("jds", jds.packed, ti.i32)
        self._value = storage.put("value", jds.value, self._mat3)
        self.hr = storage.get("hr", jds.nnz, self._mat3)          # (H R) per block
        self.ht = storage.get("ht", jds.n_active, self._mat3)     # (H T) per row
        self._scratch_for_W(1, 1)                   # sized by add_to, the one launch that writes them
        self._sizes[:N_ROTATED] = jds.n_active, len(jds.jd_ptr) - 1, jds.nnz, len(jds.touched), 0, 0, 0, 1, 0, 0
        self._reals[:] = self.solver.dt, self.inverse_mass, self._tol
        self._scalars = storage.put("sizes", self._sizes, ti.i32), storage.put("reals", self._reals, real)

    def _scratch_for_W(self, n_u: int, n_qt: int) -> None:
        """U (Q Hrᵀ per (row, dof)) and Qt (Q among the touched dofs) with room for n_u and n_qt
        entries: only forming W writes them (W's factors go to the stage's buffers), so a stage
        that keeps W as its factors does not grow them step after step, nor rebuild the launches'
        argpack and record their launches again each time."""
        self.U = self.storage.get("U", n_u, self._vec3)
        self._Qt = self.storage.get("Qt", n_qt, self.real)

    def _pack(self):
        """The argpack of the rotations' and W's launches (WARP), rebuilt only when one of its
        arrays was re-allocated."""
        arrays = (*self._shared(), self._element_rotations, *self.solver.fem.model.gather_index(), self.U, self.ht,
                  self._Qt, self._before)
        self._kept_packs["warp"] = kept_pack(self._kept_packs.get("warp"), WARP, arrays)
        return self._kept_packs["warp"][0]

    def _correction_pack(self, lam):
        """The correction's argpack (CORRECTION), λ written first."""
        arrays = (*self._shared(), self.storage.put("lam", lam, self.real), self.r0, self.pushed, self.solver.x,
                  self.solver.v)
        self._kept_packs["correction"] = kept_pack(self._kept_packs.get("correction"), CORRECTION, arrays)
        return self._kept_packs["correction"][0]

    def _shared(self) -> tuple:
        """The arrays of SHARED_MEMBERS, in their order."""
        return self.R, self.C0, self.rows, self.hr, self._jds, self._value, *self._scalars

    def _read_source(self, touched: np.ndarray) -> np.ndarray:
        """C0 from the cutting compliance followed, and per touched node its block of rows in C0.
        W and the correction read only the touched nodes' rows, so after a cut (lazy factors
        pending, changed since the last step read them) these rows of C − T Uᵀ are gathered into
        a compact array, k n (rank + 1) work; when a step finds the factors as the last one read
        them (contact goes on, the cut does not), they are folded into C (n² rank, once) and C is
        read in place from then on."""
        source = self.source
        changed, self._version = source.version != self._version, source.version
        if source.rank and changed:
            k = 3 * len(touched)
            if self._gathered is None or self._gathered.shape[0] < k or self._gathered.shape[1] != source.capacity:
                rows = k if self._gathered is None else max(k, 2 * self._gathered.shape[0])
                self._gathered = ti.ndarray(ti.f64, (rows, source.capacity))
                # Zeroed (columns past the body's dofs stay zero: the correction reads them) by a
                # copy, which is numpy's on the CPU (tissue.launch); fill() compiles a kernel of Taichi's.
                self._gathered.from_numpy(np.zeros((rows, source.capacity)))
            source.rows_into((3 * touched[:, None] + np.arange(3)).reshape(-1), self._gathered)
            self.C0 = self._gathered
            return np.arange(len(touched), dtype=np.int32)
        source.fold()
        self.C0 = source.C
        return touched

    @property
    def free(self) -> bool:
        """No node held: the rigid translation is kept apart from the warping (see above)."""
        return self.inverse_mass != 0.0

    def factor_size(self, jds: JaggedDiagonal) -> int:
        """The dofs of this body's factor for the rows `jds`: 3 per touched node, and 3 for the
        translation of a free body."""
        return 3 * len(jds.touched) + 3 * self.free

    def add_to(self, W: np.ndarray) -> None:
        """W (n_rows², the backend's float type) += h (H R) A₀⁻¹ (H R)ᵀ."""
        if not self.jds.n_active:
            return
        self._sizes[N_ROWS], self._sizes[LD_BEFORE] = W.shape[0], 0
        # Q among the touched nodes is gathered again only for other rows (or another C0): at rest
        # the rows are kept, and Qt still holds it (reading the scattered entries of C0 was about
        # half the launch's time on the floor scene).
        self._sizes[GATHER] = self._qt_rows is not self.jds or self.source is not None
        self.storage.put("sizes", self._sizes, ti.i32)
        d = 3 * len(self.jds.touched)
        self._scratch_for_W(self.jds.n_active * d, d * d)
        flat, in_place = _whole(W)
        _assemble_replayed(self._pack(), flat, self.serial)
        self._qt_rows = self.jds
        if not in_place:
            W[...] = flat[:W.size].reshape(W.shape)
        self._ready = True

    def factor(self, P: np.ndarray, Q: np.ndarray, diagonal: np.ndarray, pos: np.ndarray, q_offset: int = 0,
               pos_offset: int = 0, before: tuple | None = None) -> None:
        """This body's factors of W (tissue.contact.FactoredDelassus): P[pos[pos_offset + e]] = (H R)
        block of JDS entry e (and P[pos[pos_offset + nnz + i]] = (H T) of sorted block row i, free
        bodies), its compliance on the factor's dofs in Q from q_offset (factor_size(jds)²
        entries, row-major), and W's diagonal blocks += this body's part. (The stage hands the
        same buffers each step, whole: the launch replays.) before: (Q, q_offset, touched nodes) of
        this body's factor one step earlier, in a buffer this one does not write: its entries
        between nodes touched both times are copied from there (not with a cutting compliance,
        whose A₀⁻¹ changes)."""
        if not self.jds.n_active:
            return
        Qb, ld_before = Q, 0
        if before is not None and self.source is None and len(before[2]):
            Qb, q_before, touched = before
            at = np.minimum(touched.searchsorted(self.jds.touched), len(touched) - 1)
            index = np.where(touched[at] == self.jds.touched, at, -1).astype(np.int32)
            self._before = self.storage.put("before", index, ti.i32)
            self._sizes[Q_BEFORE], ld_before = q_before, 3 * len(touched) + 3 * self.free
        self._sizes[Q_OFFSET], self._sizes[POS_OFFSET], self._sizes[LD_BEFORE] = q_offset, pos_offset, ld_before
        self.storage.put("sizes", self._sizes, ti.i32)
        _factor_replayed(self._pack(), P, Q, Qb, diagonal, pos, self.serial)
        self._ready = True

    def correct(self, lam: np.ndarray) -> None:
        """x += R h A₀⁻¹ (H R)ᵀ λ and v += that / h, in the solver's arrays."""
        if not self.jds.n_active:
            return
        if not self._ready:
            self.storage.put("sizes", self._sizes, ti.i32)
            _rotate_replayed(self._pack(), self.serial)
            self._ready = True
        _correct_replayed(self._correction_pack(lam), self.serial)


def _whole(W: np.ndarray) -> tuple[np.ndarray, bool]:
    """W as flat memory for a kernel: the whole 1-D buffer it is the start of, when it is one
    (the pipeline's, kept between steps: the launch, keyed by the buffer's address and shape,
    replays whatever W's size), else W flat; and whether that is W's memory (else a copy, W not
    being C-contiguous, to be copied back)."""
    if not W.flags.c_contiguous:
        return np.ascontiguousarray(W).reshape(-1), False
    base = W
    while isinstance(base.base, np.ndarray):
        base = base.base
    if (base.ndim == 1 and base.flags.c_contiguous and base.dtype == W.dtype
            and base.__array_interface__["data"][0] == W.__array_interface__["data"][0]):
        return base, True
    return W.reshape(-1), True
