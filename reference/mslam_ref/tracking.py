"""Paper §3.3 — Tracking: the pose of a frame against the last keyframe by IRLS Gauss-Newton.

Each keyframe pixel n is matched to a frame pixel ``idx_f2k[n]``; the frame's point there,
``Xf_n`` (camera f), should land on the keyframe's canonical point ``Xk_n`` (camera k) once
moved by the relative similarity ``T_CkCf``. Without calibration the error is measured as
a *ray* (direction, 3) plus a lightly weighted *distance* (1) — paper Eq. (6); with known K
as a pixel (2) plus log-depth (1) error (``mslam_ref.calib``, paper §3.7). Residuals are
whitened by ``sqrt(q)/sigma``, Huber-weighted per component, and the 7x7 normal equations
``H tau = g`` (paper Eq. 7) are solved by Cholesky; ``T_CkCf <- Exp(tau) T_CkCf`` (left
retraction, paper Eq. 1).

Weights. The paper divides each residual by ``w(q, sigma^2) = sigma^2 / q`` (Eq. 5), i.e. it
treats ``sigma^2 / q`` as the *variance* of the residual. Whitening by the square root of the
information, ``r -> sqrt(q)/sigma · r``, gives exactly the IRLS weight ``W = q / sigma^2`` in
``J^T W J`` of Eq. (7); that is what the code (and upstream) does. Matches whose confidence
``Q <= Q_conf`` get weight 0 (the paper's ``w = inf``). See docs/tracking_backend.md.

Sign convention (tracker.py): ``r = z - h(T)``, ``J = dr/dxi = -dh/dxi``, ``H = A^T A``,
``g = -A^T b`` with ``A = a J``, ``b = a r`` and ``a`` the robust sqrt information.

Public names, in reading order:
    TrackingConfig, TrackingInfo, match_quality, tracking_masks, match_fraction,
    ray_dist_residual_and_jacobian, check_problem, linearize, solve, solve_with,
    keyframe_overlap, needs_new_keyframe
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from mslam_ref import calib, robust, sim3
from mslam_ref.conventions import (
    BoolArray,
    FloatArray,
    IntArray,
    as_flat_bool,
    as_flat_float,
    as_flat_index,
    as_float_array,
    as_points,
)
from mslam_ref.gauss_newton import cholesky_step, gauss_newton, small_change
from mslam_ref.pointmap import check_K

__all__ = [
    "TrackingConfig",
    "TrackingInfo",
    "check_problem",
    "keyframe_overlap",
    "linearize",
    "match_fraction",
    "match_quality",
    "needs_new_keyframe",
    "ray_dist_residual_and_jacobian",
    "solve",
    "solve_with",
    "tracking_masks",
]


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Upstream's ``tracking.*`` keys (config/base.yaml) with their defaults.

    ``tracking.filtering_mode`` / ``filtering_score`` live in ``fusion.FusionConfig``.
    """

    min_match_frac: float = 0.05
    max_iters: int = 50
    C_conf: float = 0.0
    Q_conf: float = 1.5
    rel_error: float = 1e-3
    delta_norm: float = 1e-3
    huber: float = 1.345
    match_frac_thresh: float = 0.333
    sigma_ray: float = 0.003
    sigma_dist: float = 10.0
    sigma_pixel: float = 1.0
    sigma_depth: float = 10.0
    sigma_point: float = 0.05
    pixel_border: int = -10
    depth_eps: float = 1e-6


@dataclasses.dataclass(frozen=True)
class TrackingInfo:
    """Outcome of :func:`solve`.

    Attributes:
        iterations: Gauss-Newton steps taken (linearisations).
        cost: the last cost evaluated (at the estimate *before* the last update).
        converged: a stopping test fired before ``max_iters``.
        failed: the Cholesky factorisation failed (the pose is returned unchanged).
        costs: the cost of every iteration, in order.
    """

    iterations: int
    cost: float
    converged: bool
    failed: bool
    costs: tuple[float, ...] = ()


# --- frontend helpers (paper §3.3-3.4; docs/upstream.md §5.1, §5.5) ------------------------------------------------------


def match_quality(Q_ff: FloatArray, Q_kf: FloatArray, idx_f2k: IntArray) -> FloatArray:
    """Per-keyframe-pixel match quality ``Q_k[n] = sqrt(Q_ff[idx_f2k[n]] · Q_kf[n])``.

    Paper: §3.3, ``q_{m,n} = sqrt(Q^f_{f,m} Q^k_{f,n})``. Upstream: tracker.py::track.

    Args:
        Q_ff: (N,) or (H, W) descriptor confidences of the frame (frame pixels).
        Q_kf: (N,) or (H, W) descriptor confidences of the keyframe (keyframe pixels).
        idx_f2k: (N,) or (H, W) frame pixel matched to each keyframe pixel.

    Returns:
        (N,) quality per keyframe pixel.
    """
    Q_ff = as_flat_float(Q_ff, "Q_ff", nonneg=True)
    idx = as_flat_index(idx_f2k, "idx_f2k", len(Q_ff))
    Q_kf = as_flat_float(Q_kf, "Q_kf", len(idx), nonneg=True)
    return np.sqrt(Q_ff[idx] * Q_kf)


def tracking_masks(
    valid_match_k: BoolArray,
    C_f: FloatArray,
    C_k: FloatArray,
    Q_k: FloatArray,
    cfg: TrackingConfig = TrackingConfig(),
) -> tuple[BoolArray, BoolArray]:
    """Masks of the pixels used for the pose (``valid_opt``) and for the keyframe test.

    Upstream: tracker.py::track.

        valid_opt = valid_match_k & (C_f > C_conf) & (C_k > C_conf) & (Q_k > Q_conf)
        valid_kf  = valid_match_k & (Q_k > Q_conf)

    Args:
        valid_match_k: (N,) matching succeeded for keyframe pixel n.
        C_f: (N,) average confidence of the *matched frame pixel*, ``(C/N)_f[idx_f2k]``.
        C_k: (N,) average confidence of the keyframe pixel, ``(C/N)_k``.
        Q_k: (N,) match quality (:func:`match_quality`).
        cfg: tracking configuration (``C_conf``, ``Q_conf``).

    Returns:
        valid_opt: (N,) bool; valid_kf: (N,) bool.
    """
    vm = as_flat_bool(valid_match_k, "valid_match_k")
    n = len(vm)
    C_f = as_flat_float(C_f, "C_f", n)
    C_k = as_flat_float(C_k, "C_k", n)
    Q_k = as_flat_float(Q_k, "Q_k", n)
    valid_kf = vm & (Q_k > cfg.Q_conf)
    valid_opt = valid_kf & (C_f > cfg.C_conf) & (C_k > cfg.C_conf)
    return valid_opt, valid_kf


def match_fraction(valid_opt: BoolArray) -> float:
    """Share of keyframe pixels usable for tracking; below ``min_match_frac`` the frame is
    skipped and relocalisation is tried (docs/upstream.md §5.1)."""
    v = as_flat_bool(valid_opt, "valid_opt")
    return float(v.mean()) if len(v) else 0.0


def keyframe_overlap(
    idx_f2k: IntArray, valid_match_k: BoolArray, valid_kf: BoolArray, n_cells: int | None = None
) -> float:
    """How much of the keyframe the frame still sees, in [0, 1]: the new-keyframe test's
    statistic, ``min(mean(valid_kf), |unique(idx_f2k[valid_match_k])| / n_cells)``.

    Paper: §3.4 (first sentence). Upstream: tracker.py::track (docs/upstream.md §5.5; the code
    counts distinct *frame* pixels, the paper says keyframe pixels).

    Args:
        idx_f2k: (N,) frame pixel matched to each keyframe pixel (the frame has N pixels too).
        valid_match_k: (N,) bool; valid_kf: (N,) bool from :func:`tracking_masks`.
        n_cells: the values ``idx_f2k`` can take when it holds cells of frame pixels (1..N).
    """
    vm = as_flat_bool(valid_match_k, "valid_match_k")
    if (n := len(vm)) == 0:
        raise ValueError("valid_match_k: empty mask")
    idx = as_flat_index(idx_f2k, "idx_f2k", n)
    if len(idx) != n:
        raise ValueError(f"idx_f2k: expected {n} entries, got {len(idx)}")
    vk = as_flat_bool(valid_kf, "valid_kf", n)
    cells = n if n_cells is None else int(n_cells)
    if not 1 <= cells <= n:
        raise ValueError(f"n_cells: expected 1..{n}, got {n_cells}")
    return float(min(vk.mean(), len(np.unique(idx[vm])) / cells))  # match_frac_k, unique_frac_f


def needs_new_keyframe(
    idx_f2k: IntArray,
    valid_match_k: BoolArray,
    valid_kf: BoolArray,
    cfg: TrackingConfig = TrackingConfig(),
    n_cells: int | None = None,
) -> bool:
    """New-keyframe test (paper §3.4, threshold ω_k = ``cfg.match_frac_thresh``, 0.333;
    upstream tracker.py::track): True when :func:`keyframe_overlap` (same arguments) is below
    the threshold."""
    return bool(keyframe_overlap(idx_f2k, valid_match_k, valid_kf, n_cells) < cfg.match_frac_thresh)


# --- residuals --------------------------------------------------------------------------------


def _ray_dist(X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit ray and distance; the origin maps to ray 0, distance 0 (no NaN)."""
    d = np.linalg.norm(X, axis=-1)
    d_safe = np.where(d > 0.0, d, 1.0)
    return X / d_safe[..., None], d


def ray_dist_residual_and_jacobian(
    T_CkCf: FloatArray, X_f: FloatArray, X_k: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Ray + distance residual of uncalibrated tracking and its Jacobian.

    Paper: §3.3, Eq. (6) (ray error; distance term in the text below it). Upstream:
    tracker.py::opt_pose_ray_dist_sim3,
    geometry.py::point_to_ray_dist.

        P_n = T_CkCf · Xf_n,  psi(X) = X/|X|
        r_n = [psi(Xk_n) - psi(P_n),  |Xk_n| - |P_n|]                        (Eq. 6)
        J_n = -[[(I - psi psi^T)/|P|], [psi^T]] · [I | -[P]x | P]
            = -[[(I - psi psi^T)/|P| | -[psi]x | 0], [psi^T | 0 | |P|]]      (4 x 7)

    A point at the origin gets ray 0, distance 0 and a zero Jacobian.

    Args:
        T_CkCf: (8,) Sim(3).
        X_f: (N, 3) or (H, W, 3) frame points in camera f.
        X_k: (N, 3) or (H, W, 3) keyframe points in camera k.

    Returns:
        r: (N, 4); J: (N, 4, 7).
    """
    X_k = as_points(X_k, "X_k")
    X_f = as_points(X_f, "X_f", len(X_k))
    P, dP = sim3.act_and_jacobian(T_CkCf, X_f)
    psi_k, d_k = _ray_dist(X_k)
    psi, d = _ray_dist(P)
    inv_d = np.where(d > 0.0, 1.0 / np.where(d > 0.0, d, 1.0), 0.0)
    eye = np.eye(3)
    dpsi = inv_d[:, None, None] * (eye - psi[:, :, None] * psi[:, None, :])
    dh_dP = np.concatenate([dpsi, psi[:, None, :]], axis=1)  # (N, 4, 3)
    r = np.concatenate([psi_k - psi, (d_k - d)[:, None]], axis=1)
    return r, -(dh_dP @ dP)


# --- linearisation and the IRLS driver ----------------------------------------------------------


def check_problem(
    X_f: Any, X_k: Any, Q: Any, valid: Any, K: Any
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray, FloatArray | None]:
    """Validate the inputs of :func:`linearize` / :func:`solve` (shapes, finiteness, counts).

    Returns:
        X_f (N, 3) flat; X_k as given; Q (N,); valid (N,) bool; K (3, 3) or None.
    """
    X_k = as_float_array(X_k, "X_k", 3)
    if K is not None:
        K = check_K(K)
        if X_k.ndim != 3:
            raise ValueError(f"X_k: calibrated tracking needs the (H, W, 3) grid, got {X_k.shape}")
    elif X_k.ndim not in (2, 3):
        raise ValueError(f"X_k: expected (N, 3) or (H, W, 3), got {X_k.shape}")
    n = X_k.size // 3
    X_f = as_points(X_f, "X_f", n)
    Q = as_flat_float(Q, "Q", n, nonneg=True)
    valid = as_flat_bool(valid, "valid", n)
    return X_f, X_k, Q, valid, K


def linearize(
    T_CkCf: FloatArray,
    X_f: FloatArray,
    X_k: FloatArray,
    Q: FloatArray,
    valid: BoolArray,
    cfg: TrackingConfig = TrackingConfig(),
    K: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, float]:
    """Robust normal equations of one IRLS step at the current estimate.

    Paper: §3.3, Eq. (5) (weights) and Eq. (7) (normal equations). Upstream: tracker.py::solve (and the residual set-up of
    opt_pose_ray_dist_sim3 / opt_pose_calib_sim3).

        sqrt_info = valid · sqrt(q) · [1/sigma_ray x3, 1/sigma_dist]        (uncalibrated)
                  = valid · valid_proj · valid_meas · sqrt(q) · [1/sigma_pixel x2, 1/sigma_depth]
        w~ = sqrt_info ⊙ r,  rho = huber_weight(w~, cfg.huber)   (per component)
        a = sqrt_info ⊙ sqrt(rho),  A = a ⊙ J,  b = a ⊙ r
        H = A^T A,  g = -A^T b,  cost = 1/2 b^T b

    Args:
        T_CkCf: (8,) current estimate.
        X_f: (N, 3) or (H, W, 3) frame points matched to each keyframe pixel (camera f).
        X_k: (N, 3) or (H, W, 3) keyframe canonical points (camera k); (H, W, 3) when K is
            given (the grid gives the measured pixels). In calibrated mode the caller passes
            X_f and X_k constrained to their rays (``calib.constrain_points_to_ray`` before
            indexing with ``idx_f2k``), as upstream does.
        Q: (N,) match quality (>= 0).
        valid: (N,) ``valid_opt``.
        cfg: sigmas, ``huber``, ``pixel_border``, ``depth_eps``.
        K: None for the ray + distance residual, (3, 3) intrinsics for pixel + log-depth.

    Returns:
        H: (7, 7); g: (7,); cost: float.
    """
    X_f, X_k, Q, valid, K = check_problem(X_f, X_k, Q, valid, K)
    sq = np.sqrt(Q) * valid
    if K is None:
        r, J = ray_dist_residual_and_jacobian(T_CkCf, X_f, X_k)
        sigma = np.array([cfg.sigma_ray] * 3 + [cfg.sigma_dist])
    else:
        r, J, valid_rj = calib.calib_residual_and_jacobian(T_CkCf, X_f, X_k, K, cfg)
        sq = sq * valid_rj
        sigma = np.array([cfg.sigma_pixel] * 2 + [cfg.sigma_depth])
    sqrt_info = sq[:, None] / sigma
    a = sqrt_info * np.sqrt(robust.huber_weight(sqrt_info * r, cfg.huber))
    A = (a[..., None] * J).reshape(-1, 7)
    b = (a * r).reshape(-1)
    return A.T @ A, -(A.T @ b), 0.5 * float(b @ b)


LinearizeFn = Callable[..., tuple[FloatArray, FloatArray, float]]


def solve_with(
    linearize_fn: LinearizeFn,
    X_f: Any,
    X_k: Any,
    Q: Any,
    valid: Any,
    T_CkCf_init: Any,
    cfg: TrackingConfig,
    K: Any,
) -> tuple[FloatArray, TrackingInfo]:
    """:func:`solve` with another linearisation (a kernel with :func:`linearize`'s signature
    returning ``(H, g, cost)``), run by the shared driver ``mslam_ref.gauss_newton``.
    Inputs are used as given (call :func:`check_problem` first)."""
    T0 = sim3.validate(T_CkCf_init, "T_CkCf_init")
    if T0.shape != (8,):
        raise ValueError(f"T_CkCf_init: expected shape (8,), got {T0.shape}")

    def step(T: FloatArray) -> tuple[FloatArray | None, float]:
        H, g, cost = linearize_fn(T, X_f, X_k, Q, valid, cfg, K)
        return cholesky_step(H, g), cost

    T, trace = gauss_newton(
        T0, step, sim3.retract, small_change(cfg.rel_error, cfg.delta_norm), cfg.max_iters
    )
    last = trace.costs[-1] if trace.costs else 0.0
    info = TrackingInfo(trace.iterations, last, trace.converged, trace.aborted, trace.costs)
    return T, info


def solve(
    X_f: FloatArray,
    X_k: FloatArray,
    Q: FloatArray,
    valid: BoolArray,
    T_CkCf_init: FloatArray,
    cfg: TrackingConfig = TrackingConfig(),
    K: FloatArray | None = None,
) -> tuple[FloatArray, TrackingInfo]:
    """Relative pose ``T_CkCf`` by IRLS Gauss-Newton (all 7 DoF, scale included).

    Paper: §3.3, Eq. (7) and Eq. (1) (the update). Upstream: tracker.py::opt_pose_ray_dist_sim3 /
    opt_pose_calib_sim3.

        repeat up to max_iters:
            H, g, cost = linearize(T)          (cost at the current, pre-update estimate)
            tau = chol_solve(H, g);  T <- Exp(tau) T
            stop if |(old_cost - cost)/old_cost| < rel_error or |tau| < delta_norm

    At step 0 ``old_cost = inf`` and only the ``|tau|`` test can stop. A failed Cholesky (H not
    positive definite, e.g. no valid pixel) returns the initial pose with ``failed=True``;
    upstream then relocalises. The caller composes ``T_WCf = T_WCk · T_CkCf``.

    Args:
        X_f, X_k, Q, valid, K: as :func:`linearize` (calibrated: ray-constrained by the caller).
        T_CkCf_init: (8,) initial guess (``T_WCk^-1 T_WCf`` of the previous frame).
        cfg: tracking configuration.

    Returns:
        T_CkCf: (8,) estimate; info: :class:`TrackingInfo`.
    """
    X_f, X_k, Q, valid, K = check_problem(X_f, X_k, Q, valid, K)
    return solve_with(linearize, X_f, X_k, Q, valid, T_CkCf_init, cfg, K)
