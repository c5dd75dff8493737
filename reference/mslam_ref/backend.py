"""Paper §3.5 — Backend: global Gauss-Newton over all keyframe poses of the graph.

Every graph edge (i, j) holds matches both ways; it gives two *directed blocks*. Block
(i <- j) loops over the pixels k of keyframe j, moves their canonical points into camera i
with ``T_ij = T_WCi^-1 T_WCj`` and compares them with the canonical point of the matched
pixel ``m = idx[k]`` of keyframe i: a ray + distance error without calibration, a pixel +
log-depth error with known K (paper Eq. 9, 10). Only poses are optimised. Each block gives a
14x14 Hessian block ``[[H_ii, H_ij], [H_ji, H_jj]]`` and gradient ``[g_i, g_j]``, summed into
a sparse 7(K'-1) system over the K' keyframes in the graph; the first is held fixed (the
gauge: without it the Hessian has 7 zero eigenvalues, as a Sim(3) of the whole map changes
no residual), and the system is solved by Cholesky and applied by left retraction, at most
10 times (paper §3.5; docs/tracking_backend.md).

Sign convention (gn_kernels.cu): ``e = prediction - measurement``, ``J = de/dxi`` for left
perturbations of the *world* poses, ``g = J^T W e`` and the step ``dx = -H^-1 g``.
With ``J_loc = de/d(left perturbation at P)``, ``J_j = J_loc Ad(T_WCi)^-1`` and ``J_i = -J_j``.

The data that stays fixed while the poses move (pointmaps, confidences, the directed blocks,
the intrinsics in calibrated mode) is one :class:`PoseGraph`, validated once by
:func:`pose_graph`, which constrains calibrated pointmaps to their rays (idempotent). Both live
in ``mslam_ref.backend_graph`` and are importable from here.

Public names, in reading order:
    BackendConfig, BackendInfo, directed_blocks, block_residual_and_jacobian, PoseGraph,
    pose_graph, check_poses, linearize, solve, solve_with
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from mslam_ref import calib, robust, sim3
from mslam_ref.backend_graph import PoseGraph, check_poses, pose_graph
from mslam_ref.conventions import BoolArray, FloatArray, IntArray
from mslam_ref.gauss_newton import gauss_newton
from mslam_ref.normal_equations import assemble_system, factor_solve

__all__ = [
    "BackendConfig",
    "BackendInfo",
    "PoseGraph",
    "block_residual_and_jacobian",
    "check_poses",
    "directed_blocks",
    "linearize",
    "pose_graph",
    "solve",
    "solve_with",
]

#: Huber threshold of the backend (hard-coded in gn_kernels.cu).
HUBER_K = robust.HUBER_K


@dataclasses.dataclass(frozen=True)
class BackendConfig:
    """Upstream's ``local_opt.*`` keys (config/base.yaml) with their defaults
    (``window_size`` and ``use_cuda`` are read but unused upstream)."""

    pin: int = 1
    window_size: float = 1e6
    C_conf: float = 0.0
    Q_conf: float = 1.5
    min_match_frac: float = 0.1
    pixel_border: int = -10
    depth_eps: float = 1e-6
    max_iters: int = 10
    sigma_ray: float = 0.003
    sigma_dist: float = 10.0
    sigma_pixel: float = 1.0
    sigma_depth: float = 10.0
    sigma_point: float = 0.05
    delta_norm: float = 1e-8
    use_cuda: bool = True


@dataclasses.dataclass(frozen=True)
class BackendInfo:
    """Outcome of :func:`solve`.

    Attributes:
        iterations: Gauss-Newton iterations run.
        costs: robust cost ``1/2 sum W e^2`` of every iteration, before its update.
        step_norms: ``|dx|`` of every iteration.
        failed: iterations whose factorisation failed (a zero step, as upstream).
        keyframes: the sorted keyframe indices in the graph; ``keyframes[:pin]`` stay fixed.
    """

    iterations: int
    costs: tuple[float, ...]
    step_norms: tuple[float, ...]
    failed: int
    keyframes: tuple[int, ...]

    @property
    def cost(self) -> float:
        """The cost of the last iteration (0.0 when nothing ran)."""
        return self.costs[-1] if self.costs else 0.0


def directed_blocks(
    ii: IntArray,
    jj: IntArray,
    idx_i2j: IntArray,
    idx_j2i: IntArray,
    valid_match_j: BoolArray,
    valid_match_i: BoolArray,
    Q_j: FloatArray,
    Q_i: FloatArray,
) -> tuple[IntArray, IntArray, IntArray, BoolArray, FloatArray]:
    """Two directed blocks per stored edge (upstream global_opt.py::prep_two_way_edges).

    Edge e = (i, j) gives (i <- j) with ``idx_i2j, valid_match_j, Q_j`` over the pixels of j,
    then (j <- i) with ``idx_j2i, valid_match_i, Q_i`` over the pixels of i.

    Args:
        ii, jj: (E,) keyframe indices; idx_*: (E, N) int; valid_*: (E, N) bool; Q_*: (E, N).

    Returns:
        ii_d, jj_d: (2E,); idx: (2E, N); valid: (2E, N); Q: (2E, N).
    """
    ii, jj = np.asarray(ii, np.int64).reshape(-1), np.asarray(jj, np.int64).reshape(-1)
    cat = lambda a, b: np.concatenate([np.asarray(a), np.asarray(b)], axis=0)
    return (
        cat(ii, jj),
        cat(jj, ii),
        cat(idx_i2j, idx_j2i).astype(np.int64),
        cat(valid_match_j, valid_match_i).astype(bool),
        cat(Q_j, Q_i).astype(np.float64),
    )


def block_residual_and_jacobian(
    T_WCi: FloatArray,
    T_WCj: FloatArray,
    X_i: FloatArray,
    X_j: FloatArray,
    C_i: FloatArray,
    C_j: FloatArray,
    idx: IntArray,
    valid: BoolArray,
    Q: FloatArray,
    cfg: BackendConfig = BackendConfig(),
    K: FloatArray | None = None,
    pixels: IntArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Residuals, pose Jacobians and sqrt weights of one directed block (i <- j).

    Paper: §3.5, Eq. (9) (rays); §3.7, Eq. (10) (pixels, known K). Upstream:
    gn_kernels.cu::ray_align_kernel / calib_proj_kernel.

        m = idx[k] if valid[k] else 0,  P = T_WCi^-1 T_WCj · Xj[k]
        ok = valid & q > Q_conf & C_i[m] > C_conf & C_j[k] > C_conf
        ray:   e = [psi(P) - psi(Xi[m]), |P| - |Xi[m]|],   w = ok sqrt(q) [1/s_ray x3, 1/s_dist]
        calib: e = [u - m mod W, v - m div W, log P_z - log Xi_z[m]],
               w = ok valid_uv valid_z sqrt(q) [1/s_pixel x2, 1/s_depth]
        J_loc = de/dP [I | -[P]x | P],  J_j = J_loc Ad(T_WCi)^-1,  J_i = -J_j

    Args:
        T_WCi, T_WCj: (8,) world poses.
        X_i, X_j: (H, W, 3) canonical pointmaps (ray-constrained by the caller when K given).
        C_i, C_j: (H, W) average confidences.
        idx: (N,) pixel of i matched to each pixel of j; valid: (N,) bool; Q: (N,) quality.
        cfg: backend configuration.
        K: None (ray + distance) or (3, 3) intrinsics (pixel + log-depth).
        pixels: (N,) the pixels k of j that carry the residuals, in the order of ``idx``
            (None: every pixel, N = H·W).

    Returns:
        e: (N, c); J_i: (N, c, 7); J_j: (N, c, 7); w: (N, c) sqrt weights (0 where invalid),
        with c = 4 (ray) or 3 (calibrated). Rows with w = 0 may hold any finite value.
    """
    H, W = X_j.shape[:2]
    Xi, Xj, C_j = X_i.reshape(-1, 3), X_j.reshape(-1, 3), C_j.reshape(-1)
    if pixels is not None:
        Xj, C_j = Xj[pixels], C_j[pixels]
    m = np.where(valid, idx, 0)
    Xim = Xi[m]
    ok = valid & (Q > cfg.Q_conf) & (C_i.reshape(-1)[m] > cfg.C_conf) & (C_j > cfg.C_conf)
    sq = np.sqrt(np.maximum(Q, 0.0)) * ok
    P, dP = sim3.act_and_jacobian(sim3.mul(sim3.inv(T_WCi), T_WCj), Xj)
    if K is None:
        d = np.linalg.norm(P, axis=-1)
        d_safe = np.where(d > 0.0, d, 1.0)
        psi = P / d_safe[:, None]
        di = np.linalg.norm(Xim, axis=-1)
        psi_i = Xim / np.where(di > 0.0, di, 1.0)[:, None]
        e = np.concatenate([psi - psi_i, (d - di)[:, None]], axis=1)
        dpsi = (np.eye(3) - psi[:, :, None] * psi[:, None, :]) / d_safe[:, None, None]
        de_dP = np.concatenate([dpsi, psi[:, None, :]], axis=1)
        w = sq[:, None] / np.array([cfg.sigma_ray] * 3 + [cfg.sigma_dist])
    else:
        pz, de_dP, valid_proj = calib.project_calib_and_jacobian(
            P, K, (H, W), cfg.pixel_border, cfg.depth_eps
        )
        zi = Xim[:, 2]
        valid_zi = zi > cfg.depth_eps
        target = np.stack([m % W, m // W, np.log(np.where(valid_zi, zi, 1.0))], -1)
        e = np.where(valid_zi[:, None], pz - target, 0.0)
        w = (sq * valid_proj * valid_zi)[:, None] / np.array(
            [cfg.sigma_pixel] * 2 + [cfg.sigma_depth]
        )
    J_loc = de_dP @ dP
    J_j = sim3.adjoint_inv_apply(T_WCi, J_loc)
    return e, -J_j, J_j, w


def linearize(
    T_WC: FloatArray, graph: PoseGraph, cfg: BackendConfig = BackendConfig()
) -> tuple[FloatArray, FloatArray, float]:
    """Hessian blocks, gradients and robust cost of the D directed blocks.

    Paper: §3.5, Eq. (9) and the 14x14 blocks of the 7N x 7N Hessian below it. Upstream:
    gn_kernels.cu::ray_align_kernel /
    calib_proj_kernel (the per-block reduction). Per pixel and residual component c:

        W_c = huber(w_c e_c) w_c^2        (Huber per component, k = 1.345)
        H_ii += W_c J_i^T J_i,  H_ij += W_c J_i^T J_j,  H_ji = H_ij^T,  H_jj += W_c J_j^T J_j
        g_i += W_c e_c J_i,     g_j += W_c e_c J_j,     cost += 1/2 W_c e_c^2

    Args:
        T_WC: (K, 8) keyframe poses (camera to world).
        graph: the :class:`PoseGraph` (pointmaps, blocks, intrinsics).
        cfg: backend configuration.

    Returns:
        Hs: (D, 4, 7, 7) ``[H_ii, H_ij, H_ji, H_jj]``; gs: (D, 2, 7) ``[g_i, g_j]``; cost.
    """
    T_WC = check_poses(T_WC, graph)
    g = graph
    D = g.n_blocks
    Hs, gs, cost = np.zeros((D, 4, 7, 7)), np.zeros((D, 2, 7)), 0.0
    for d in range(D):  # blocks (few), each vectorised over its N pixels
        i, j = g.ii[d], g.jj[d]
        e, J_i, J_j, w = block_residual_and_jacobian(
            T_WC[i], T_WC[j], g.X[i], g.X[j], g.C[i], g.C[j], g.idx[d], g.valid[d], g.Q[d], cfg,
            g.K_cam, g.pixels,
        )  # fmt: skip
        W = robust.huber_weight(w * e, HUBER_K) * w * w  # (N, c)
        sW = np.sqrt(W)
        A_i, A_j = (sW[..., None] * J_i).reshape(-1, 7), (sW[..., None] * J_j).reshape(-1, 7)
        b = (sW * e).reshape(-1)
        Hs[d] = [A_i.T @ A_i, A_i.T @ A_j, A_j.T @ A_i, A_j.T @ A_j]
        gs[d] = [A_i.T @ b, A_j.T @ b]
        cost += 0.5 * float(b @ b)
    return Hs, gs, cost


LinearizeFn = Callable[..., tuple[FloatArray, FloatArray, float]]


def solve_with(
    linearize_fn: LinearizeFn, T_WC: Any, graph: PoseGraph, cfg: BackendConfig
) -> tuple[FloatArray, BackendInfo]:
    """:func:`solve` with another linearisation (a kernel with :func:`linearize`'s signature),
    run by the shared driver ``mslam_ref.gauss_newton``."""
    T_WC = check_poses(T_WC, graph)
    kf = np.unique(np.concatenate([graph.ii, graph.jj]))
    pin = int(cfg.pin)
    if len(kf) <= pin:
        return T_WC.copy(), BackendInfo(0, (), (), 0, tuple(int(k) for k in kf))
    pos_i, pos_j = np.searchsorted(kf, graph.ii) - pin, np.searchsorted(kf, graph.jj) - pin
    n = len(kf) - pin
    free = kf[pin:]

    def step(T: FloatArray) -> tuple[FloatArray | None, float]:
        Hs, gs, cost = linearize_fn(T, graph, cfg)
        A, b = assemble_system(
            np.asarray(Hs, np.float64), np.asarray(gs, np.float64), pos_i, pos_j, n
        )
        return factor_solve(A, b), cost

    def retract(T: FloatArray, dx: FloatArray) -> FloatArray:
        T = T.copy()
        T[free] = sim3.retract(T[free], dx.reshape(n, 7))
        return T

    stop = lambda old, cost, dx: float(np.linalg.norm(dx)) < cfg.delta_norm
    T, trace = gauss_newton(T_WC.copy(), step, retract, stop, cfg.max_iters, np.zeros(7 * n))
    keyframes = tuple(int(k) for k in kf)
    return T, BackendInfo(trace.iterations, trace.costs, trace.step_norms, trace.failed, keyframes)


def solve(
    T_WC: FloatArray, graph: PoseGraph, cfg: BackendConfig = BackendConfig()
) -> tuple[FloatArray, BackendInfo]:
    """Global Gauss-Newton over the poses of the keyframes in the graph.

    Paper: §3.5 (Gauss-Newton "as in Eq. (7)", sparse Cholesky). Upstream:
    global_opt.py::FactorGraph.solve_GN_rays / solve_GN_calib,
    gn_kernels.cu::gauss_newton_rays / gauss_newton_calib.

        kf = sorted unique(ii ∪ jj); kf[:pin] fixed (gauge; upstream pin = 1)
        repeat max_iters (10):
            Hs, gs = linearize(T);  A, b = assemble_system(...)   (7(K'-pin) unknowns)
            dx = -A^-1 b  (Cholesky; dx = 0 if it fails);  T_WC[kf[pin:]] <- Exp(dx) T_WC
            stop if |dx| < delta_norm (1e-8: in practice all iterations run)

    No damping (as upstream). The dense Cholesky of ``A.toarray()`` is used up to 7 x 511
    unknowns (upstream's 512-keyframe buffer), sparse LU beyond. Keyframes not in the graph
    keep their pose.

    Args:
        T_WC: (K, 8) keyframe poses; graph: the :class:`PoseGraph`; cfg: configuration.

    Returns:
        T_WC: (K, 8) updated poses; info: :class:`BackendInfo`.
    """
    return solve_with(linearize, T_WC, graph, cfg)
