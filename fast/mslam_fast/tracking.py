"""Taichi twin of ``mslam_ref.tracking`` — same names, parameters and shapes; see there for
the maths.

``linearize``: one fused kernel computes, per keyframe pixel, the residual (ray + distance, or
pixel + log-depth with K), its Jacobian, the sqrt information and the per-component Huber
weight, and accumulates ``W J J^T`` (upper triangle), ``W r J`` and ``1/2 W r^2``.
Parallel axis: chunks of :data:`CHUNK` pixels, one thread per chunk; each chunk sums into its
own row of an (n_chunks, 36) float64 array (no atomics), the host sums the rows in chunk order.
Residuals and Jacobians run in the runtime float type, every sum in float64.

Ray + distance mode: the three ray rows are accumulated in closed form
(``_kernels.tracking.accumulate_rays``) and the pixel loop is branch-free, with points passed
as flat ``(3N,)`` arrays (a compile-time stride), so LLVM vectorises it over pixels (4 f64 /
8 f32 lanes; the reduction order within a chunk is then LLVM's). Calibrated mode is
branch-free too (rows one by one, ``log`` by ``_kernels.tracking.log_pos``).

``solve`` is the reference IRLS driver (``mslam_ref.tracking.solve_with``, which runs
``mslam_ref.gauss_newton``) with this ``linearize``; inputs are validated and converted once,
not per iteration. The frontend helpers (masks, match quality, keyframe test) have no kernel:
use ``mslam_ref.tracking``'s.
"""

from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._device import to_device
from mslam_fast._kernels import sim3 as S
from mslam_fast._kernels import tracking as KT
from mslam_fast._runtime import ensure_init
from mslam_fast._types import nd, template
from mslam_ref import sim3 as _sim3
from mslam_ref import tracking as ref_tracking
from mslam_ref.tracking import TrackingConfig, TrackingInfo

__all__ = ["linearize", "solve"]

Array = np.ndarray[Any, Any]

CHUNK = KT.CHUNK


@ti.kernel
def _linearize_k(T: nd, Xf: nd, Xk: nd, Q: nd, valid: nd, prm: nd, out: nd, calib: template):
    n = Q.shape[0]
    for c in range(out.shape[0]):
        acc = ti.Vector.zero(ti.f64, KT.NACC)
        Tv = S.load(T, 0, 8)
        s1_inv = ti.cast(1.0 / prm[0], float)
        s2_inv = ti.cast(1.0 / prm[1], float)
        hk = ti.cast(prm[2], float)
        for k in range(c * CHUNK, ti.min(c * CHUNK + CHUNK, n)):
            if ti.static(not calib):  # branch-free: an invalid pixel gets zero inputs, weight 0
                ok = valid[k] != 0
                zero3 = ti.Vector([0.0, 0.0, 0.0])
                sq = ti.sqrt(ti.select(ok, Q[k], 0.0))
                P = S.sim3_act(Tv, ti.select(ok, KT.load3(Xf, k), zero3))
                p, d, inv_d = KT.unit_norm_inv(P)
                pk, dk = KT.unit_and_norm(ti.select(ok, KT.load3(Xk, k), zero3))
                KT.accumulate_rays(acc, p, inv_d, pk - p, sq * s1_inv, hk)
                e, si = dk - d, sq * s2_inv
                Jd = ti.Vector([p[0], p[1], p[2], 0.0, 0.0, 0.0, d])  # distance row
                KT.accumulate(acc, Jd, e, si * si * KT.huber(si * e, hk), KT.ZERO_DIST)
            else:  # branch-free as well: a rejected pixel gets a safe point and weight 0
                fx, fy = ti.cast(prm[3], float), ti.cast(prm[4], float)
                cx, cy = ti.cast(prm[5], float), ti.cast(prm[6], float)
                border, eps = ti.cast(prm[7], float), ti.cast(prm[8], float)
                Wf, Hf = ti.cast(prm[9], float), ti.cast(prm[10], float)
                P = S.sim3_act(Tv, KT.load3(Xf, k))
                zk = Xk[3 * k + 2]
                ok_z = (valid[k] != 0) & (zk > eps) & (P[2] > eps)
                safe = ti.Vector([0.0, 0.0, 1.0])
                # Rows at the safe point are finite; outside the image e = 0 and w = 0 below.
                uv, J = KT.calib_rows(ti.select(ok_z, P, safe), fx, fy, cx, cy)
                ok = (
                    ok_z
                    & (uv[0] > border)
                    & (uv[0] < Wf - 1.0 - border)
                    & (uv[1] > border)
                    & (uv[1] < Hf - 1.0 - border)
                )
                sq = ti.sqrt(ti.select(ok, Q[k], 0.0))
                lzk = ti.cast(KT.log_pos(ti.select(ok_z, zk, 1.0)), float)
                # Pixel (u, v) of k without integer division (no SIMD form): exact for k < 2^24
                # since (k + 0.5)/W stays >= 0.5/W away from an integer.
                kf = ti.cast(k, float)
                vf = ti.floor((kf + 0.5) / Wf)
                meas = ti.Vector([kf - vf * Wf, vf, lzk])
                for r in ti.static(range(3)):
                    e = ti.select(ok, meas[r] - uv[r], 0.0)
                    si = sq * s2_inv
                    if ti.static(r < 2):
                        si = sq * s1_inv
                    w = si * si * KT.huber(si * e, hk)
                    KT.accumulate(acc, KT.row(J, r), e, w, KT.ZERO_CALIB[r])
        KT.store_acc(out, c, acc)


def _unpack(acc: Array) -> tuple[Array, Array, float]:
    """(36,) accumulator -> symmetric H (7, 7), g (7,), cost."""
    Hm = np.zeros((7, 7))
    rows, cols = zip(*KT.TRI, strict=True)
    Hm[rows, cols] = acc[:28]
    Hm[cols, rows] = acc[:28]
    return Hm, acc[28:35].copy(), float(acc[35])


def _prepared(X_f: Array, X_k: Array, Q: Array, valid: Array) -> tuple[Array, Array, Array, Array]:
    dtype = ensure_init().dtype
    c = lambda a, s: np.ascontiguousarray(a.reshape(s), dtype=dtype)
    return c(X_f, (-1, 3)), c(X_k, (-1, 3)), c(Q, (-1,)), np.ascontiguousarray(valid, np.uint8)


def _params(cfg: TrackingConfig, K: Array | None, shape: tuple[int, ...]) -> Array:
    if K is None:
        return np.array([cfg.sigma_ray, cfg.sigma_dist, cfg.huber] + [0.0] * 8)
    H, W = shape[:2]
    return np.array(
        [
            cfg.sigma_pixel,
            cfg.sigma_depth,
            cfg.huber,
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            cfg.pixel_border,
            cfg.depth_eps,
            W,
            H,
        ],
        dtype=np.float64,
    )


def _linearize_prepared(
    T: Array,
    X_f: Array,
    X_k: Array,
    Q: Array,
    valid: Array,
    cfg: TrackingConfig,
    K: Any,
    shape: tuple[int, ...],
) -> tuple[Array, Array, float]:
    """Kernel call on inputs already validated and converted by :func:`_prepared`: ``X_f`` and
    ``X_k`` flat (3N,), all four host arrays or device arrays (``mslam_fast._device``)."""
    n = Q.shape[0]
    n_chunks = max(1, -(-n // CHUNK))
    out = np.zeros((n_chunks, KT.NACC))
    if n:
        T_ = np.asarray(T, np.float64).reshape(1, 8).astype(ensure_init().dtype)
        prm = _params(cfg, K, shape)
        _linearize_k(T_, X_f, X_k, Q, valid, prm, out, K is not None)
    return _unpack(out.sum(axis=0))


def linearize(
    T_CkCf: Any,
    X_f: Any,
    X_k: Any,
    Q: Any,
    valid: Any,
    cfg: TrackingConfig = TrackingConfig(),  # noqa: B008 (frozen, immutable)
    K: Any = None,
) -> tuple[Array, Array, float]:
    """Taichi twin of ``mslam_ref.tracking.linearize`` (H, g, cost in float64)."""
    X_f, X_k, Q, valid, K = ref_tracking.check_problem(X_f, X_k, Q, valid, K)
    T = _sim3.validate(T_CkCf, "T_CkCf")
    if T.shape != (8,):
        raise ValueError(f"T_CkCf: expected shape (8,), got {T.shape}")
    Xf, Xk, Qp, vp = _prepared(X_f, X_k, Q, valid)
    return _linearize_prepared(T, Xf.reshape(-1), Xk.reshape(-1), Qp, vp, cfg, K, X_k.shape)


def solve(
    X_f: Any,
    X_k: Any,
    Q: Any,
    valid: Any,
    T_CkCf_init: Any,
    cfg: TrackingConfig = TrackingConfig(),  # noqa: B008
    K: Any = None,
) -> tuple[Array, TrackingInfo]:
    """Taichi twin of ``mslam_ref.tracking.solve``: the reference driver, this linearize.

    The converted inputs go to the device once per solve (``mslam_fast._device.to_device``),
    not once per iteration."""
    X_f, X_k, Q, valid, K = ref_tracking.check_problem(X_f, X_k, Q, valid, K)
    shape = X_k.shape
    Xf, Xk, Qp, vp = _prepared(X_f, X_k, Q, valid)
    n = len(Qp)
    labels = ("tracking.X_f", "tracking.X_k", "tracking.Q", "tracking.valid")
    flat = (Xf.reshape(-1), Xk.reshape(-1), Qp, vp)
    d = [to_device(a, label) if n else a for a, label in zip(flat, labels, strict=True)]
    lin = lambda T, Xf_, Xk_, Q_, v_, c, KK: _linearize_prepared(
        T, d[0], d[1], d[2], d[3], c, KK, shape
    )
    return ref_tracking.solve_with(lin, Xf, Xk, Qp, vp, T_CkCf_init, cfg, K)
