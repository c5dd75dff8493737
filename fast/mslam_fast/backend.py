"""Taichi twin of ``mslam_ref.backend`` — same names, parameters and shapes; see there for the
maths.

``linearize``: one fused kernel over (directed block, pixel chunk) pairs, so both cores work
even for a single block: per pixel k of j it gathers the matched point of i, moves X_j with
``T_ij`` (computed once per chunk), forms the ray + distance (or, with K, pixel + log-depth
on the ray-constrained points) residual, its local rows ``J_loc`` and the Huber weight, and
accumulates ``W J_loc^T J_loc``, ``W e J_loc`` and ``1/2 W e^2`` in float64 into its own row
of a (D, n_chunks, 36) array (no atomics). The host sums the chunks and applies the chain
rule once per block: with ``M = Ad(T_WCi)^-1`` (``J_j = J_loc M``), ``H_jj = M^T H_loc M``
and ``g_j = M^T g_loc``. Since ``J_i = -J_j`` exactly, ``H_ii = H_jj``,
``H_ij = H_ji = -H_jj`` and ``g_i = -g_j``. Per-pixel maths runs in the runtime float type,
sums in float64. Both pixel loops are branch-free and vectorised over pixels as in
``mslam_fast.tracking`` (ray rows in closed form, X as a flat ``(3·n_kf·N,)`` array).

``solve`` is the reference Gauss-Newton driver (``mslam_ref.backend.solve_with``: sparse
assembly, Cholesky, retraction on the host) with this linearisation.
"""

from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._kernels import sim3 as S
from mslam_fast._kernels import tracking as KT
from mslam_fast._runtime import ensure_init
from mslam_fast._types import nd, template
from mslam_ref import backend as ref_backend
from mslam_ref import sim3 as _sim3
from mslam_ref.backend import BackendConfig, BackendInfo, PoseGraph

__all__ = ["linearize", "solve"]

Array = np.ndarray[Any, Any]

CHUNK = KT.CHUNK


@ti.kernel
def _linearize_k(
    T: nd,
    X: nd,
    C: nd,
    ii: nd,
    jj: nd,
    idx: nd,
    valid: nd,
    Q: nd,
    pix: nd,
    prm: nd,
    out: nd,
    calib: template,
):
    n = C.shape[1]
    n_cols = pix.shape[0]
    n_chunks = out.shape[1]
    for d, c in ti.ndrange(out.shape[0], n_chunks):
        acc = ti.Vector.zero(ti.f64, KT.NACC)
        i = ii[d]
        j = jj[d]
        Tij = S.sim3_mul(S.sim3_inv(S.load(T, i, 8)), S.load(T, j, 8))
        s1_inv = ti.cast(1.0 / prm[0], float)
        s2_inv = ti.cast(1.0 / prm[1], float)
        Q_conf, C_conf = ti.cast(prm[2], float), ti.cast(prm[3], float)
        fx, fy = ti.cast(prm[4], float), ti.cast(prm[5], float)
        cx, cy = ti.cast(prm[6], float), ti.cast(prm[7], float)
        border, eps = ti.cast(prm[8], float), ti.cast(prm[9], float)
        Wd = ti.cast(prm[10], ti.i32)
        Hd = ti.cast(prm[11], ti.i32)
        for t in range(c * CHUNK, ti.min(c * CHUNK + CHUNK, n_cols)):
            k = pix[t]  # the pixel of j of column t
            q = Q[d, t]
            m = idx[d, t]
            if ti.static(not calib):  # branch-free (vectorised): a rejected pixel has weight 0
                # `&`, not `and` (short-circuit branches would keep the loop scalar)
                ok = (valid[d, t] != 0) & (q > Q_conf) & (C[i, m] > C_conf) & (C[j, k] > C_conf)
                zero3 = ti.Vector([0.0, 0.0, 0.0])
                sq = ti.sqrt(ti.select(ok, q, 0.0))
                P = S.sim3_act(Tij, ti.select(ok, KT.load3(X, j * n + k), zero3))
                p, dd, inv_d = KT.unit_norm_inv(P)
                pi, di = KT.unit_and_norm(ti.select(ok, KT.load3(X, i * n + m), zero3))
                KT.accumulate_rays(acc, p, inv_d, p - pi, sq * s1_inv, KT.HUBER_K)
                e, si = dd - di, sq * s2_inv
                Jd = ti.Vector([p[0], p[1], p[2], 0.0, 0.0, 0.0, dd])  # distance row
                KT.accumulate(acc, Jd, e, si * si * KT.huber(si * e, KT.HUBER_K), KT.ZERO_DIST)
            else:  # branch-free as well: a rejected pixel gets a safe point and weight 0
                ok_c = (valid[d, t] != 0) & (q > Q_conf) & (C[i, m] > C_conf) & (C[j, k] > C_conf)
                zj = X[3 * (j * n + k) + 2]
                Xj = ti.Vector(  # constrain X_j to the ray of pixel k
                    [
                        zj * (ti.cast(k % Wd, float) - cx) / fx,
                        zj * (ti.cast(k // Wd, float) - cy) / fy,
                        zj,
                    ]
                )
                P = S.sim3_act(Tij, Xj)
                zi = X[3 * (i * n + m) + 2]
                ok_z = ok_c & (zi > eps) & (P[2] > eps)
                safe = ti.Vector([0.0, 0.0, 1.0])
                uv, _J = KT.calib_rows(ti.select(ok_z, P, safe), fx, fy, cx, cy)
                ok = (
                    ok_z
                    & (uv[0] > border)
                    & (uv[0] < Wd - 1 - border)
                    & (uv[1] > border)
                    & (uv[1] < Hd - 1 - border)
                )
                _uv, J = KT.calib_rows(ti.select(ok, P, safe), fx, fy, cx, cy)  # finite rows
                sq = ti.sqrt(ti.select(ok, q, 0.0))
                lzi = ti.cast(KT.log_pos(ti.select(ok_z, zi, 1.0)), float)
                tgt = ti.Vector([ti.cast(m % Wd, float), ti.cast(m // Wd, float), lzi])
                for r in ti.static(range(3)):
                    e = ti.select(ok, uv[r] - tgt[r], 0.0)
                    si = sq * s2_inv
                    if ti.static(r < 2):
                        si = sq * s1_inv
                    w = si * si * KT.huber(si * e, KT.HUBER_K)
                    KT.accumulate(acc, KT.row(J, r), e, w, KT.ZERO_CALIB[r])
        for t in ti.static(range(18)):
            out[d, c, t] = acc[t]
        for t in ti.static(range(18, KT.NACC)):
            out[d, c, t] = acc[t]


def _params(cfg: BackendConfig, K: Array | None, H: int, W: int) -> Array:
    if K is None:
        s1, s2, f = cfg.sigma_ray, cfg.sigma_dist, (1.0, 1.0, 0.0, 0.0)
    else:
        s1, s2, f = cfg.sigma_pixel, cfg.sigma_depth, (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return np.array(
        [s1, s2, cfg.Q_conf, cfg.C_conf, *f, cfg.pixel_border, cfg.depth_eps, W, H], np.float64
    )


def linearize(
    T_WC: Any,
    graph: PoseGraph,
    cfg: BackendConfig = BackendConfig(),  # noqa: B008 (frozen)
) -> tuple[Array, Array, float]:
    """Taichi twin of ``mslam_ref.backend.linearize`` (Hs, gs and cost in float64). In
    calibrated mode the kernel applies the ray constraint itself (idempotent)."""
    T_WC = ref_backend.check_poses(T_WC, graph)
    g, K = graph, graph.K_cam
    dtype = ensure_init().dtype
    n_kf, H, W = g.X.shape[:3]
    D, N = g.n_blocks, H * W
    Hs, gs = np.zeros((D, 4, 7, 7)), np.zeros((D, 2, 7))
    if D == 0:
        return Hs, gs, 0.0
    pix = np.arange(N) if g.pixels is None else g.pixels
    n_cols = len(pix)
    out = np.zeros((D, max(1, -(-n_cols // CHUNK)), KT.NACC))
    c = lambda a, s, t=dtype: np.ascontiguousarray(np.reshape(a, s), dtype=t)
    _linearize_k(
        c(T_WC, (n_kf, 8)),
        c(g.X, (-1,)),
        c(g.C, (n_kf, N)),
        c(g.ii, (D,), np.int32),
        c(g.jj, (D,), np.int32),
        c(g.idx, (D, n_cols), np.int32),
        c(g.valid, (D, n_cols), np.uint8),
        c(g.Q, (D, n_cols)),
        c(pix, (n_cols,), np.int32),
        _params(cfg, K, H, W),
        out,
        K is not None,
    )
    acc = out.sum(axis=1)
    rows, cols = zip(*KT.TRI, strict=True)
    H_loc = np.zeros((D, 7, 7))
    H_loc[:, rows, cols] = acc[:, :28]
    H_loc[:, cols, rows] = acc[:, :28]
    # J_j = J_loc M with M = Ad(T_WCi)^-1 (row r of M: e_r M), once per block, not per row
    M = _sim3.adjoint_inv_apply(T_WC[g.ii][:, None, :], np.eye(7)[None])
    Hjj = np.einsum("dra,drs,dsb->dab", M, H_loc, M)
    g_j = np.einsum("dra,dr->da", M, acc[:, 28:35])
    Hs[:, 0], Hs[:, 1], Hs[:, 2], Hs[:, 3] = Hjj, -Hjj, -Hjj, Hjj
    gs[:, 0], gs[:, 1] = -g_j, g_j
    return Hs, gs, float(acc[:, 35].sum())


def solve(
    T_WC: Any,
    graph: PoseGraph,
    cfg: BackendConfig = BackendConfig(),  # noqa: B008
) -> tuple[Array, BackendInfo]:
    """Taichi twin of ``mslam_ref.backend.solve``: the reference driver, this linearize."""
    return ref_backend.solve_with(linearize, T_WC, graph, cfg)
