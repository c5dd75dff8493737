"""Two-view geometry for the classical prior — dense flow, essential matrix, triangulation.

The maths of :mod:`mslam.priors.twoview`, image pair (i, j) with intrinsics K:

* dense correspondences ``u_j = u_i + F_ij(u_i)`` from OpenCV's DIS optical flow
  (:mod:`mslam.priors.twoview_dis`), checked forward–backward:
  ``e_fb(u_i) = ‖F_ij(u_i) + F_ji(u_i + F_ij(u_i))‖`` (pixels);
* the essential matrix ``x_jᵀ E x_i = 0`` (``x = K⁻¹[u, 1]``) by RANSAC on a subsample of the
  consistent correspondences, decomposed into ``X_j = R_ji X_i + t_ji`` with ``‖t_ji‖ = 1``
  (cheirality decides among the four solutions);
* midpoint triangulation in camera i: rays ``a = K⁻¹[u_i, 1]`` from the origin and
  ``b = R_jiᵀ K⁻¹[u_j, 1]`` from the centre ``c_j = -R_jiᵀ t_ji``; depths (λ, μ) minimise
  ``‖λ a - (c_j + μ b)‖²``, the point is the midpoint; the triangulation angle is ∠(a, b);
* parallax of the pair from the best homography H (RANSAC), not from the essential matrix,
  whose translation (and so the triangulation angle) is noise when the baseline is tiny: the
  residuals ``‖u_j - H u_i‖`` (a non-planar scene) and the departure of ``K⁻¹ H K`` from a
  rotation (a plane seen from two centres). Pure rotation and a tiny baseline give ~0 for both
  (:mod:`mslam.priors.twoview_homography`, re-exported here).

Public names, in reading order:
    focal_guess_intrinsics, forward_backward_error, symmetric_flow, flow_consistency,
    essential_pose, sampson_residuals, sampson_distances, refine_pose, homography_parallax,
    triangulate_midpoint, front_counts, reprojection_error
"""

from __future__ import annotations

import cv2
import numpy as np

from mslam.priors.twoview_homography import homography_parallax
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import intrinsics_from_fov

__all__ = [
    "essential_pose",
    "focal_guess_intrinsics",
    "forward_backward_error",
    "homography_parallax",
    "refine_pose",
    "reprojection_error",
    "sampson_distances",
    "sampson_residuals",
    "symmetric_flow",
    "flow_consistency",
    "triangulate_midpoint",
    "front_counts",
]

#: Horizontal field of view assumed when no calibration is given (degrees). 60° is the middle
#: of the usual webcam / phone / Kinect range (Kinect v1: 57°, TUM fr1: 63°, phones: 60–70°).
GUESS_FOV_DEG = 60.0


def focal_guess_intrinsics(width: int, height: int, fov_deg: float = GUESS_FOV_DEG) -> FloatArray:
    """Pinhole K of an uncalibrated camera: ``f = (L / 2) / tan(fov / 2)`` with L the image's
    long side, centred.

    A camera's field of view belongs to its sensor's long side: a phone held upright films
    portrait frames whose *width* is the short side, and a guess across the width would make
    its focal length a third too short (the 7-Scenes clip turned upright: 104 px against about
    131 at 120x160; RGB-only ATE 3.79 cm with the guess across the width, 3.00 cm across the
    long side, 2026-11-27, docs/priors.md). Landscape frames are unchanged.

    Args:
        width, height: image size in pixels (>= 2).
        fov_deg: assumed field of view across the long side (default 60°: ``f ≈ 0.866 L``).

    Returns:
        (3, 3) float64, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``, square pixels.
    """
    K = intrinsics_from_fov(width, height, fov_deg)
    if height > width:
        K[0, 0] = K[1, 1] = K[0, 0] * height / width
    return K


def _grid(H: int, W: int) -> FloatArray:
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    return np.stack([u, v], axis=-1)


def forward_backward_error(F_ij: FloatArray, F_ji: FloatArray) -> tuple[FloatArray, np.ndarray]:
    """Forward–backward consistency ``e = ‖F_ij(u) + F_ji(u + F_ij(u))‖`` (bilinear lookup)
    of (H, W, 2) flows: ``e`` (H, W) in pixels (``inf`` where ``u + F_ij(u)`` leaves image j)
    and ``inside`` (H, W) bool, whether ``u + F_ij(u)`` lies in image j."""
    back, inside = _back_flow(F_ij, F_ji)
    return _fb_error(F_ij, back, inside), inside


def symmetric_flow(F_ij: FloatArray, F_ji: FloatArray) -> FloatArray:
    """(H, W, 2) float64: the mean of the forward flow and the reversed backward flow,
    ``½ (F_ij(u) − F_ji(u + F_ij(u)))`` (bilinear lookup; ``F_ij`` where ``u + F_ij(u)``
    leaves image j), from (H, W, 2) flows ``F_ij``, ``F_ji``.

    Where the two flows disagree by ``e_fb`` pixels, the pointmaps triangulated from ``F_ij``
    (pixels of i) and ``F_ji`` (pixels of j) give one scene point depths that differ by about
    ``e_fb / parallax``. Both views triangulated along their symmetric flow use (to first
    order) the same correspondence, and the mean of two flow estimates is the less noisy one
    (measurements: docs/priors.md)."""
    return flow_consistency(F_ij, F_ji)[2]


def flow_consistency(
    F_ij: FloatArray, F_ji: FloatArray
) -> tuple[FloatArray, np.ndarray, FloatArray]:
    """:func:`forward_backward_error` ``(e, inside)`` and :func:`symmetric_flow` of one pair
    from one lookup of ``F_ji(u + F_ij(u))``: (H, W), (H, W) bool, (H, W, 2)."""
    back, inside = _back_flow(F_ij, F_ji)
    F_sym = np.where(inside[..., None], 0.5 * (F_ij - back), F_ij)
    return _fb_error(F_ij, back, inside), inside, F_sym


def _fb_error(F_ij: FloatArray, back: FloatArray, inside: np.ndarray) -> FloatArray:
    """``‖F_ij + back‖`` (H, W), ``inf`` outside image j."""
    return np.where(inside, np.linalg.norm(F_ij + back, axis=-1), np.inf)


def _back_flow(F_ij: FloatArray, F_ji: FloatArray) -> tuple[FloatArray, np.ndarray]:
    """``F_ji(u + F_ij(u))`` (H, W, 2) float64 by bilinear lookup (border replicated), and
    whether ``u + F_ij(u)`` lies in image j (H, W)."""
    H, W = F_ij.shape[:2]
    target = _grid(H, W) + F_ij
    inside = (
        (target[..., 0] >= 0)
        & (target[..., 0] <= W - 1)
        & (target[..., 1] >= 0)
        & (target[..., 1] <= H - 1)
    )
    m = target.astype(np.float32)
    back = cv2.remap(F_ji.astype(np.float32), m[..., 0], m[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
    return back.astype(np.float64), inside


def essential_pose(
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    ransac_px: float = 1.0,
    confidence: float = 0.999,
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Relative pose ``X_j = R_ji X_i + t_ji`` (``‖t_ji‖ = 1``) from correspondences, RANSAC.

    Args:
        uv_i, uv_j: (N, 2) corresponding pixels (N >= 5).
        K: (3, 3) intrinsics shared by both images.
        ransac_px: RANSAC threshold (pixels, on the epipolar distance).
        confidence: RANSAC confidence.

    Returns:
        R_ji (3, 3), t_ji (3,), inliers (N,) bool (RANSAC inliers that also pass cheirality).
        On failure (no model) the identity, zeros and an all-False mask.
    """
    uv_i = np.ascontiguousarray(uv_i, dtype=np.float64).reshape(-1, 2)
    uv_j = np.ascontiguousarray(uv_j, dtype=np.float64).reshape(-1, 2)
    n = len(uv_i)
    fail = (np.eye(3), np.zeros(3), np.zeros(n, bool))
    if n < 5 or len(uv_j) != n:
        return fail
    try:
        E, mask = cv2.findEssentialMat(uv_i, uv_j, K, cv2.RANSAC, confidence, ransac_px)
    except cv2.error:
        return fail
    if E is None or E.shape != (3, 3) or mask is None:
        return fail  # several solutions (a (3k, 3) stack) are rare; treat as failure
    try:
        # distanceThresh: points farther than this (in units of the baseline) count as at
        # infinity and fail cheirality; with small baselines most points are > 50 baselines
        # away (OpenCV's default of the short overload), so allow 1e4.
        _, R, t, pose_mask, _ = cv2.recoverPose(
            E, uv_i, uv_j, K, distanceThresh=1e4, mask=mask.copy()
        )
    except cv2.error:
        return fail
    inl = pose_mask.ravel() > 0
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return fail
    return R.astype(np.float64), t.ravel().astype(np.float64), inl


def sampson_residuals(
    uv_i: FloatArray, uv_j: FloatArray, K: FloatArray, R_ji: FloatArray, t_ji: FloatArray
) -> FloatArray:
    """Signed Sampson distances (pixels) of correspondences to the epipolar geometry.

    ``F = K⁻ᵀ [t]ₓ R K⁻¹``, ``r = x_jᵀ F x_i / sqrt((F x_i)₁² + (F x_i)₂² + (Fᵀx_j)₁² + (Fᵀx_j)₂²)``
    with homogeneous pixels ``x``.

    Args:
        uv_i, uv_j: (N, 2). K: (3, 3). R_ji (3, 3), t_ji (3,).

    Returns:
        (N,) residuals.
    """
    tx = np.array([[0, -t_ji[2], t_ji[1]], [t_ji[2], 0, -t_ji[0]], [-t_ji[1], t_ji[0], 0]])
    Kinv = np.linalg.inv(K)
    return sampson_distances(Kinv.T @ tx @ R_ji @ Kinv, uv_i, uv_j)


def sampson_distances(F: FloatArray, uv_i: FloatArray, uv_j: FloatArray) -> FloatArray:
    """Signed Sampson distances (pixels) of correspondences to a fundamental matrix ``F``
    (3, 3) with ``x_jᵀ F x_i = 0`` (formula of :func:`sampson_residuals`); ``uv_i``, ``uv_j``
    (N, 2); returns (N,)."""
    ones = np.ones((len(uv_i), 1))
    xi, xj = np.hstack([uv_i, ones]), np.hstack([uv_j, ones])
    Fxi, Ftxj = xi @ F.T, xj @ F
    num = (xj * Fxi).sum(-1)
    den = np.sqrt(Fxi[:, 0] ** 2 + Fxi[:, 1] ** 2 + Ftxj[:, 0] ** 2 + Ftxj[:, 1] ** 2)
    return num / np.maximum(den, 1e-12)


def refine_pose(
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    R_ji: FloatArray,
    t_ji: FloatArray,
    huber_px: float = 0.3,
) -> tuple[FloatArray, FloatArray]:
    """Refine ``(R_ji, t_ji)`` on all inliers: robust least squares on Sampson distances.

    RANSAC's model is fitted to 5 correspondences; with small baselines its rotation and
    translation trade off against each other. Parameters: a rotation increment ``ω``
    (``R = Exp(ω) R₀``) and two coordinates ``a`` of ``t = normalize(t₀ + B a)``, B (3, 2) an
    orthonormal basis of the plane orthogonal to ``t₀`` (the length of t is not observable).
    Huber loss with ``huber_px``.

    Args:
        uv_i, uv_j: (N, 2) inlier correspondences. K: (3, 3). R_ji (3, 3), t_ji (3,).

    Returns:
        R_ji (3, 3), t_ji (3,) with ``‖t_ji‖ = 1`` (the input when the solver fails).
    """
    from mslam.priors.twoview_lm import huber_lm, sampson_fn, so3_exp

    t0 = t_ji / np.linalg.norm(t_ji)
    B = np.linalg.svd(t0[None, :])[2][1:].T
    residuals = sampson_fn(uv_i, uv_j, K)

    def unpack(P):  # (M, 5) parameter sets -> R (M, 3, 3), t (M, 3)
        t = t0 + (B[:, 0] * P[:, 3:4] + B[:, 1] * P[:, 4:5])
        return so3_exp(P[:, :3]) @ R_ji, t / np.linalg.norm(t, axis=1)[:, None]

    def fun(P):  # (M, 5) parameter sets -> (M, N) residuals
        return residuals(*unpack(P))

    p = huber_lm(fun, np.zeros(5), huber_px)
    if p is None:
        return R_ji, t0
    R, t = unpack(p[None])
    return R[0], t[0]


def triangulate_midpoint(
    uv_i: FloatArray, uv_j: FloatArray, K: FloatArray, R_ji: FloatArray, t_ji: FloatArray
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Midpoint triangulation of correspondences, in camera i (module docstring).

    Args:
        uv_i, uv_j: (..., 2) corresponding pixels.
        K: (3, 3). R_ji (3, 3), t_ji (3,): ``X_j = R_ji X_i + t_ji``.

    Returns:
        X_i: (..., 3) points in camera i (0 where not triangulable);
        angle: (...,) triangulation angle ∠(a, b) in radians;
        ok: (...,) bool, both depths > 0 and the rays not parallel (angle > 1e-6).
    """
    a, b, c, lam, mu, angle, valid = _midpoint_terms(uv_i, uv_j, K, R_ji, t_ji)
    X = 0.5 * (lam[..., None] * a + c + mu[..., None] * b)
    ok = valid & (lam > 0) & (mu > 0)
    return np.where(ok[..., None], X, 0.0), angle, ok


def front_counts(
    uv_i: FloatArray, uv_j: FloatArray, K: FloatArray, R_ji: FloatArray, t_ji: FloatArray
) -> tuple[int, int]:
    """How many correspondences triangulate in front of both cameras with ``t_ji`` and with
    ``-t_ji``: ``(n, n_flipped)``, the ``ok`` counts of :func:`triangulate_midpoint` for both
    signs from one pass (with ``-t`` both ray parameters change sign exactly, so a point in
    front for one sign is behind for the other)."""
    _, _, _, lam, mu, _, valid = _midpoint_terms(uv_i, uv_j, K, R_ji, t_ji)
    return int(np.sum(valid & (lam > 0) & (mu > 0))), int(np.sum(valid & (lam < 0) & (mu < 0)))


def _midpoint_terms(
    uv_i: FloatArray, uv_j: FloatArray, K: FloatArray, R_ji: FloatArray, t_ji: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, np.ndarray]:
    """The rays ``a`` and ``b`` (..., 3) of camera i and of camera j rotated into i, the
    centre ``c`` (3,) of j in i, the ray parameters ``lam``, ``mu`` (...,) of the closest
    points ``lam a`` and ``c + mu b``, the angle (...,) between the rays, and ``valid`` (...,):
    rays not parallel (angle > 1e-6)."""
    Kinv = np.linalg.inv(K)
    ones = np.ones((*uv_i.shape[:-1], 1))
    a = np.concatenate([uv_i, ones], -1) @ Kinv.T
    b = (np.concatenate([uv_j, ones], -1) @ Kinv.T) @ R_ji  # R_jiᵀ x_j, row form
    c = -(R_ji.T @ t_ji)
    aa, bb, ab = (a * a).sum(-1), (b * b).sum(-1), (a * b).sum(-1)
    ac, bc = a @ c, b @ c
    det = aa * bb - ab * ab  # >= 0, 0 for parallel rays
    safe = np.where(det > 1e-12 * aa * bb, det, 1.0)
    lam = (ac * bb - ab * bc) / safe
    mu = (ab * ac - aa * bc) / safe
    cosang = ab / np.sqrt(aa * bb)
    angle = np.arccos(np.clip(cosang, -1.0, 1.0))
    valid = (det > 1e-12 * aa * bb) & (angle > 1e-6)
    return a, b, c, lam, mu, angle, valid


def reprojection_error(
    X_i: FloatArray,
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    R_ji: FloatArray,
    t_ji: FloatArray,
) -> FloatArray:
    """Larger of the two pixel reprojection errors of points ``X_i`` (..., 3) in camera i.

    Returns:
        (...,) pixels; ``inf`` where the point is not in front of both cameras.
    """
    X_j = X_i @ R_ji.T + t_ji
    out = np.full(X_i.shape[:-1], np.inf)
    front = (X_i[..., 2] > 1e-9) & (X_j[..., 2] > 1e-9)
    err = np.zeros_like(out)
    for X, uv in ((X_i, uv_i), (X_j, uv_j)):
        z = np.where(front, X[..., 2], 1.0)
        p = (X[..., :2] / z[..., None]) * K[[0, 1], [0, 1]] + K[:2, 2]
        err = np.maximum(err, np.linalg.norm(p - uv, axis=-1))
    return np.where(front, err, out)
