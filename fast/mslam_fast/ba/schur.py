"""Taichi twin of ``mslam_ref.ba.schur`` — same names, parameters and shapes; see there for the maths.

Parallel axes and reductions (no atomics anywhere; every sum runs in a ``ti.f64`` local over a
CSR list built once by ``build_structure``, so results are deterministic):

* ``normal_blocks``: W per observation (O items); U (its upper triangle, mirrored) and bc per
  camera (M items, each summing the camera's observations); V and bl per point (P items).
* ``jacobi_scale``: D and the scaled U, bc per camera (M items), V, bl per point (P items), W per
  observation (O items).
* ``scaled_normal_blocks``: U/bc and V/bl as above, then D and the scaled blocks; the scaled W
  per observation from the Jacobians (O items), with no unscaled W in memory.
* ``schur_complement``: V^-1 per point (adjugate, P items); Y = W V^-1 and Y bl per observation
  (O items); rhs per (camera, row); S per block over the block's observation pairs (B items;
  a diagonal block sums its upper triangle only and mirrors it).
* ``back_substitute``: one point per item (P items).

The large outputs (W, the scaled W, S, Vinv) are recycled once the caller has released them
(``mslam_fast._recycle``). Inputs are coerced to the runtime dtype and their shapes checked, not scanned for NaN/inf: the
reference computes on any value (a singular damped V_j gives ``inf`` in Vinv, and the solve
fails later). ``build_structure``, ``dense_reduced`` and ``solve_reduced`` have no kernel (host set-up and a
SciPy/LAPACK Cholesky): the LM driver calls ``mslam_ref.ba.schur``'s.
"""

from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._kernels import ba as K
from mslam_fast._matching_host import _kept, _zeros
from mslam_fast._recycle import output
from mslam_fast._runtime import coerce, ensure_init
from mslam_fast._types import f64, nd, template
from mslam_ref.ba.schur import BlockStructure, pin_fixed

__all__ = [
    "back_substitute",
    "jacobi_scale",
    "normal_blocks",
    "scaled_normal_blocks",
    "schur_complement",
]

Array = np.ndarray[Any, Any]


@ti.kernel
def _W_k(Jc: nd, Jp: nd, w: nd, W: nd, d: template, k: template):
    for e in range(Jc.shape[0]):
        for i in ti.static(range(d)):
            for j in ti.static(range(3)):
                acc = ti.cast(0.0, f64)
                for m in ti.static(range(k)):
                    acc += ti.cast(Jc[e, m, i] * Jp[e, m, j], f64)
                W[e, i, j] = acc * w[e]


@ti.kernel
def _U_k(Jc: nd, w: nd, r: nd, ptr: nd, order: nd, U: nd, bc: nd, d: template,
         k: template):  # fmt: skip
    for c in range(U.shape[0]):  # one camera per item, its observations in CSR order
        acc = ti.Matrix.zero(f64, d, d)  # upper triangle only, mirrored at the end
        accb = ti.Vector.zero(f64, d)
        for q in range(ti.cast(ptr[c], ti.i32), ti.cast(ptr[c + 1], ti.i32)):
            e = order[q]
            we = ti.cast(w[e], f64)
            for m in ti.static(range(k)):
                J = ti.Vector([ti.cast(Jc[e, m, i], f64) for i in ti.static(range(d))])
                wJ = we * J
                for i in ti.static(range(d)):
                    for j in ti.static(range(i, d)):
                        acc[i, j] += wJ[i] * J[j]
                accb += r[e, m] * wJ
        for i in ti.static(range(d)):
            for j in ti.static(range(i, d)):
                U[c, i, j] = acc[i, j]
                U[c, j, i] = acc[i, j]
            bc[c, i] = -accb[i]


@ti.kernel
def _V_k(Jp: nd, w: nd, r: nd, ptr: nd, order: nd, V: nd, bl: nd, k: template):
    for p in range(V.shape[0]):
        acc = ti.Matrix.zero(f64, 3, 3)
        accb = ti.Vector.zero(f64, 3)
        for q in range(ti.cast(ptr[p], ti.i32), ti.cast(ptr[p + 1], ti.i32)):
            e = order[q]
            we = ti.cast(w[e], f64)
            for m in ti.static(range(k)):
                for i in ti.static(range(3)):
                    a = we * Jp[e, m, i]
                    accb[i] += a * r[e, m]
                    for j in ti.static(range(3)):
                        acc[i, j] += a * Jp[e, m, j]
        for i in ti.static(range(3)):
            bl[p, i] = -accb[i]
            for j in ti.static(range(3)):
                V[p, i, j] = acc[i, j]


@ti.kernel
def _jac_diag_k(A: nd, b: nd, D: nd, As: nd, bs: nd, n: template):
    for c in range(A.shape[0]):  # D, D A D and D b of one n x n block
        for i in ti.static(range(n)):
            D[c, i] = 1.0 / (1.0 + ti.sqrt(A[c, i, i]))
        for i in ti.static(range(n)):
            bs[c, i] = b[c, i] * D[c, i]
            for j in ti.static(range(n)):
                As[c, i, j] = A[c, i, j] * D[c, i] * D[c, j]


@ti.kernel
def _jac_W_k(W: nd, Dc: nd, Dp: nd, oc: nd, op: nd, Ws: nd, d: template):
    for e in range(W.shape[0]):
        c, p = oc[e], op[e]
        for i in ti.static(range(d)):
            for j in ti.static(range(3)):
                Ws[e, i, j] = W[e, i, j] * Dc[c, i] * Dp[p, j]


@ti.kernel
def _Ws_k(Jc: nd, Jp: nd, w: nd, Dc: nd, Dp: nd, oc: nd, op: nd, Ws: nd, d: template,
          k: template):  # fmt: skip
    for e in range(Jc.shape[0]):  # W_e = J_c^T w J_p scaled by Dc and Dp, never stored unscaled
        c, p = oc[e], op[e]
        for i in ti.static(range(d)):
            for j in ti.static(range(3)):
                acc = ti.cast(0.0, f64)
                for m in ti.static(range(k)):
                    acc += ti.cast(Jc[e, m, i] * Jp[e, m, j], f64)
                Ws[e, i, j] = acc * w[e] * Dc[c, i] * Dp[p, j]


@ti.kernel
def _vinv_k(V: nd, lam: f64, Vinv: nd):
    for p in range(V.shape[0]):
        A = ti.Matrix.zero(f64, 3, 3)
        for i in ti.static(range(3)):
            for j in ti.static(range(3)):
                A[i, j] = V[p, i, j]
            A[i, i] += lam
        B = K.inv3(A)
        for i in ti.static(range(3)):
            for j in ti.static(range(3)):
                Vinv[p, i, j] = B[i, j]


@ti.kernel
def _Y_k(W: nd, Vinv: nd, op: nd, bl: nd, Y: nd, t: nd, d: template):
    for e in range(W.shape[0]):
        p = op[e]
        for i in ti.static(range(d)):
            acc_t = ti.cast(0.0, f64)
            for j in ti.static(range(3)):
                acc = ti.cast(0.0, f64)
                for m in ti.static(range(3)):
                    acc += ti.cast(W[e, i, m] * Vinv[p, m, j], f64)
                Y[e, i, j] = acc
                acc_t += acc * bl[p, j]
            t[e, i] = acc_t


@ti.kernel
def _rhs_k(bc: nd, t: nd, ptr: nd, order: nd, rhs: nd):
    for c, i in ti.ndrange(bc.shape[0], bc.shape[1]):
        acc = ti.cast(0.0, f64)
        for q in range(ti.cast(ptr[c], ti.i32), ti.cast(ptr[c + 1], ti.i32)):
            acc += t[order[q], i]
        rhs[c, i] = bc[c, i] - acc


@ti.func
def _S_pairs(Y: template, W: template, pptr: template, pa: template, pb: template, b,
             d: template, upper: template):  # fmt: skip
    """-sum over the block's pairs of Y_a W_b^T (d x d, f64); only i <= j when ``upper``."""
    acc = ti.Matrix.zero(f64, d, d)
    for q in range(ti.cast(pptr[b], ti.i32), ti.cast(pptr[b + 1], ti.i32)):
        a, c = pa[q], pb[q]
        for i in ti.static(range(d)):
            y0, y1, y2 = (
                ti.cast(Y[a, i, 0], f64),
                ti.cast(Y[a, i, 1], f64),
                ti.cast(Y[a, i, 2], f64),
            )
            for j in ti.static(range(i if ti.static(upper) else 0, d)):
                acc[i, j] -= y0 * W[c, j, 0] + y1 * W[c, j, 1] + y2 * W[c, j, 2]
    return acc


@ti.kernel
def _S_k(Y: nd, W: nd, U: nd, lam: f64, brow: nd, bcol: nd, pptr: nd, pa: nd, pb: nd, S: nd,
         d: template):  # fmt: skip
    for b in range(S.shape[0]):  # one d x d block per item: Y and W blocks are loaded once
        c = brow[b]
        if c == bcol[b]:  # diagonal block: symmetric, its upper triangle mirrored
            acc = _S_pairs(Y, W, pptr, pa, pb, b, d, True)
            for i in ti.static(range(d)):
                for j in ti.static(range(i, d)):
                    v = acc[i, j] + U[c, i, j] + (lam if i == j else 0.0)
                    S[b, i, j] = v
                    S[b, j, i] = v
        else:
            acc = _S_pairs(Y, W, pptr, pa, pb, b, d, False)
            for i in ti.static(range(d)):
                for j in ti.static(range(d)):
                    S[b, i, j] = acc[i, j]


@ti.kernel
def _back_k(Vinv: nd, W: nd, bl: nd, dc: nd, ptr: nd, order: nd, oc: nd, dl: nd,
            d: template):  # fmt: skip
    for p in range(bl.shape[0]):
        acc = ti.Vector([ti.cast(bl[p, m], f64) for m in ti.static(range(3))])
        for q in range(ti.cast(ptr[p], ti.i32), ti.cast(ptr[p + 1], ti.i32)):
            e = order[q]
            c = oc[e]
            for m in ti.static(range(3)):
                s = ti.cast(0.0, f64)
                for i in ti.static(range(d)):
                    s += W[e, i, m] * dc[c, i]
                acc[m] -= s
        for m in ti.static(range(3)):
            dl[p, m] = Vinv[p, m, 0] * acc[0] + Vinv[p, m, 1] * acc[1] + Vinv[p, m, 2] * acc[2]


def _z(*shape: int) -> Array:
    return np.zeros(shape, dtype=ensure_init().dtype)


def _out(key: str, *shape: int) -> Array:
    """A recycled output (``mslam_fast._recycle``): the kernels write every element."""
    return output(key, shape, ensure_init().dtype)


def normal_blocks(
    r: Any, J_cam: Any, J_pt: Any, weight: Any, structure: BlockStructure
) -> tuple[Array, Array, Array, Array, Array]:
    """Taichi twin of ``mslam_ref.ba.schur.normal_blocks`` (W per observation, U/bc per
    (camera, row), V/bl per point; f64 accumulation over CSR lists, no atomics)."""
    s, d = structure, structure.cam_dof
    r = coerce(r, "r", None)
    k = r.shape[1]
    Jc, Jp = coerce(J_cam, "J_cam", (k, d)), coerce(J_pt, "J_pt", (k, 3))
    w = coerce(weight, "weight", None)
    O, M, P = len(r), s.n_cams, s.n_points
    U, V, W, bc, bl = _z(M, d, d), _z(P, 3, 3), _out("W", O, d, 3), _z(M, d), _z(P, 3)
    if O:
        _W_k(Jc, Jp, w, W, d, k)
        _U_k(Jc, w, r, s.cam_ptr, s.cam_obs, U, bc, d, k)
        _V_k(Jp, w, r, s.pt_ptr, s.pt_obs, V, bl, k)
    return U, V, W, bc, bl


def jacobi_scale(
    U: Any, V: Any, W: Any, bc: Any, bl: Any, structure: BlockStructure
) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
    """Taichi twin of ``mslam_ref.ba.schur.jacobi_scale`` (per camera, per point, per
    observation; no reductions)."""
    s, d = structure, structure.cam_dof
    U, V = coerce(U, "U", (d, d)), coerce(V, "V", (3, 3))
    W, bc, bl = coerce(W, "W", (d, 3)), coerce(bc, "bc", d), coerce(bl, "bl", 3)
    M, P, O = len(U), len(V), len(W)
    Us, Vs, Ws, bcs, bls, Dc, Dp = (_z(M, d, d), _z(P, 3, 3), _out("Ws", O, d, 3), _z(M, d), _z(P, 3),
                                    _z(M, d), _z(P, 3))  # fmt: skip
    if M:
        _jac_diag_k(U, bc, Dc, Us, bcs, d)
    if P:
        _jac_diag_k(V, bl, Dp, Vs, bls, 3)
    if O:
        _jac_W_k(W, Dc, Dp, s.obs_cam, s.obs_pt, Ws, d)
    return Us, Vs, Ws, bcs, bls, Dc, Dp


def scaled_normal_blocks(
    r: Any,
    J_cam: Any,
    J_pt: Any,
    weight: Any,
    cam_free: Any,
    point_free: Any,
    structure: BlockStructure,
) -> tuple[Array, Array, Array, Array, Array, Array, Array]:
    """Taichi twin of ``mslam_ref.ba.schur.scaled_normal_blocks`` (U/bc per camera, V/bl per
    point, masked and scaled on their small arrays; the scaled W per observation straight from
    the Jacobians, so the unscaled W is never stored)."""
    s, d = structure, structure.cam_dof
    r = coerce(r, "r", None)
    k = r.shape[1]
    Jc, Jp = coerce(J_cam, "J_cam", (k, d)), coerce(J_pt, "J_pt", (k, 3))
    w = coerce(weight, "weight", None)
    O, M, P = len(r), s.n_cams, s.n_points
    U, V, bc, bl = _z(M, d, d), _z(P, 3, 3), _z(M, d), _z(P, 3)
    if O:
        _U_k(Jc, w, r, s.cam_ptr, s.cam_obs, U, bc, d, k)
        _V_k(Jp, w, r, s.pt_ptr, s.pt_obs, V, bl, k)
    pin_fixed(U, V, bc, bl, np.asarray(cam_free, bool), np.asarray(point_free, bool))
    Us, Vs, bcs, bls, Dc, Dp = _z(M, d, d), _z(P, 3, 3), _z(M, d), _z(P, 3), _z(M, d), _z(P, 3)
    if M:
        _jac_diag_k(U, bc, Dc, Us, bcs, d)
    if P:
        _jac_diag_k(V, bl, Dp, Vs, bls, 3)
    Ws = _out("Ws", O, d, 3)
    if O:
        _Ws_k(Jc, Jp, w, Dc, Dp, s.obs_cam, s.obs_pt, Ws, d, k)
    return Us, Vs, Ws, bcs, bls, Dc, Dp


def schur_complement(
    U: Any, V: Any, W: Any, bc: Any, bl: Any, lam: float, structure: BlockStructure
) -> tuple[Array, Array, Array]:
    """Taichi twin of ``mslam_ref.ba.schur.schur_complement`` (V^-1 per point, Y per
    observation, rhs per (camera, row), S per (block, row) over its pair list; f64 sums)."""
    s, d = structure, structure.cam_dof
    U, V = coerce(U, "U", (d, d)), coerce(V, "V", (3, 3))
    W, bc, bl = coerce(W, "W", (d, 3)), coerce(bc, "bc", d), coerce(bl, "bl", 3)
    O, M, P = len(W), s.n_cams, s.n_points
    Vinv, rhs = _out("Vinv", P, 3, 3), _z(M, d)
    # Y and t are written whole before they are read: kept per thread and shape (fresh pages
    # cost a fault each; on CUDA they stay in GPU memory)
    Y, t = _kept(("ba_Y", O, d), lambda: (_zeros((O, d, 3)), _zeros((O, d))))
    S = _out("S", len(s.block_row), d, d)
    if P:
        _vinv_k(V, float(lam), Vinv)
    if O:
        _Y_k(W, Vinv, s.obs_pt, bl, Y, t, d)
    _rhs_k(bc, t, s.cam_ptr, s.cam_obs, rhs)
    _S_k(Y, W, U, float(lam), s.block_row, s.block_col, s.pair_ptr, s.pair_a, s.pair_b, S, d)
    return S, rhs, Vinv


def back_substitute(Vinv: Any, W: Any, bl: Any, dc: Any, structure: BlockStructure) -> Array:
    """Taichi twin of ``mslam_ref.ba.schur.back_substitute`` (one point per item)."""
    s, d = structure, structure.cam_dof
    Vinv, W = coerce(Vinv, "Vinv", (3, 3)), coerce(W, "W", (d, 3))
    bl, dc = coerce(bl, "bl", 3), coerce(dc, "dc", d)
    dl = _z(s.n_points, 3)
    if s.n_points:
        _back_k(Vinv, W, bl, dc, s.pt_ptr, s.pt_obs, s.obs_cam, dl, d)
    return dl
