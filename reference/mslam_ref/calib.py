"""Paper §3.7 — Known calibration: points on known rays, pixel + log-depth residuals.

With known intrinsics K, MASt3R-SLAM keeps the network's pointmaps but reads them *along
the known camera rays*: only the depth of each canonical point survives
(``constrain_points_to_ray``). Tracking then minimises a pixel reprojection error plus a
log-depth error instead of the ray + distance error of the uncalibrated system
(``calib_residual_and_jacobian``, docs/upstream.md §5.3). The 3-D point error of upstream's unused
``point_align_kernel`` (the point-error ablation of Table 6) is ``point_residual_and_jacobian``.

Residual convention of this module (tracker.py): ``r = z - h(T)`` (measurement minus
prediction) and ``J = dr/dxi = -dh/dxi`` for a left perturbation ``T <- Exp(xi) T``.

Public functions, in reading order:
    constrain_points_to_ray, project_calib_and_jacobian, calib_residual_and_jacobian,
    point_residual_and_jacobian
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_ref import sim3
from mslam_ref.conventions import BoolArray, FloatArray, as_float_array, as_points
from mslam_ref.pointmap import check_K

__all__ = [
    "PIXEL_BORDER",
    "Z_EPS",
    "calib_residual_and_jacobian",
    "constrain_points_to_ray",
    "point_residual_and_jacobian",
    "project_calib_and_jacobian",
]

#: Upstream defaults of ``tracking.pixel_border`` / ``local_opt.pixel_border`` and ``depth_eps``.
PIXEL_BORDER = -10
Z_EPS = 1e-6


def constrain_points_to_ray(X: FloatArray, K: FloatArray) -> FloatArray:
    """Keep only the depth of each point and put it on its pixel's known ray.

    Paper: §3.7. Upstream: mast3r_slam/geometry.py::constrain_points_to_ray.

        X(u, v) <- z(u, v) · [(u - cx)/fx, (v - cy)/fy, 1]

    Idempotent (z is unchanged). Applied on read: the stored canonical pointmap is not changed.

    Args:
        X: (..., H, W, 3) pointmap(s); the last two batch axes are the pixel grid.
        K: (3, 3) intrinsics.

    Returns:
        (..., H, W, 3) float64.
    """
    X = as_float_array(X, "X", 3)
    K = check_K(K)
    if X.ndim < 3:
        raise ValueError(f"X: expected (..., H, W, 3), got shape {X.shape}")
    H, W = X.shape[-3:-1]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return X[..., 2:3] * rays


def project_calib_and_jacobian(
    P: FloatArray,
    K: FloatArray,
    img_size: tuple[int, int],
    border: float = PIXEL_BORDER,
    z_eps: float = Z_EPS,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Project to ``[u, v, log z]`` with its Jacobian and upstream's validity rule.

    Paper: §3.7. Upstream: geometry.py::project_calib(jacobian=True).

        u = fx x/z + cx,  v = fy y/z + cy,  third component log z
        valid = border < u < W-1-border  and  border < v < H-1-border  and  z > z_eps
        d[u, v, log z]/dP = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2], [0, 0, 1/z]]

    Numerics: where ``z <= z_eps`` upstream sets ``log z = 0`` (and its u, v may be inf); here
    every output of such a point (u, v, log z and the Jacobian) is 0, so no NaN escapes.

    Args:
        P: (N, 3) points in the camera frame.
        K: (3, 3) intrinsics.
        img_size: (H, W).
        border: pixel border; negative values admit points outside the image.
        z_eps: smallest valid depth.

    Returns:
        pz: (N, 3) ``[u, v, log z]``.
        dpz_dP: (N, 3, 3).
        valid: (N,) bool.
    """
    P = as_float_array(P, "P", 3)
    K = check_K(K)
    H, W = int(img_size[0]), int(img_size[1])
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    valid_z = z > z_eps
    iz = np.where(valid_z, 1.0 / np.where(valid_z, z, 1.0), 0.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * x * iz + cx
    v = fy * y * iz + cy
    valid = valid_z & (u > border) & (u < W - 1 - border) & (v > border) & (v < H - 1 - border)
    logz = np.log(np.where(valid_z, z, 1.0))
    pz = np.where(valid_z[..., None], np.stack([u, v, logz], -1), 0.0)
    J = np.zeros((*P.shape[:-1], 3, 3))
    J[..., 0, 0] = fx * iz
    J[..., 0, 2] = -fx * x * iz * iz
    J[..., 1, 1] = fy * iz
    J[..., 1, 2] = -fy * y * iz * iz
    J[..., 2, 2] = iz
    return pz, J, valid


def calib_residual_and_jacobian(
    T_CkCf: FloatArray,
    X_f: FloatArray,
    X_k: FloatArray,
    K: FloatArray,
    cfg: Any = None,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Pixel + log-depth residual of calibrated tracking and its Jacobian.

    Paper: §3.7 (calibrated tracking; the pixel error of Eq. 10, depth as log-depth). Upstream:
    tracker.py::opt_pose_calib_sim3 (one step).

        measurement  z_n = [u_n, v_n, log Zk_n]     (u_n, v_n) = integer pixel n of the keyframe
        prediction   h_n = [u, v, log z](P_n),      P_n = T_CkCf · Xf_n
        r_n = z_n - h_n,    J_n = -d[u, v, log z]/dP · [I | -[P]x | P]

    Validity (returned, not applied to weights): ``valid_meas = Zk > depth_eps`` and the
    projection rule of :func:`project_calib_and_jacobian`. Rows of invalid pixels are 0.

    Args:
        T_CkCf: (8,) Sim(3) pose of frame f in keyframe k.
        X_f: (N, 3) or (H, W, 3) frame points matched to each keyframe pixel, in camera f,
            **already constrained to their rays by the caller** (docs/upstream.md §5.1).
        X_k: (H, W, 3) the keyframe's ray-constrained canonical pointmap (only z is used);
            its shape gives the pixel grid and the image size.
        K: (3, 3) intrinsics.
        cfg: any object with ``pixel_border`` and ``depth_eps`` (``TrackingConfig``,
            ``BackendConfig``); None uses upstream's -10 and 1e-6.

    Returns:
        r: (N, 3) residuals (N = H W, row-major pixel order ``n = u + W v``).
        J: (N, 3, 7) ``dr/dxi``.
        valid: (N,) bool, ``valid_meas & valid_proj``.
    """
    X_k = as_float_array(X_k, "X_k", 3)
    if X_k.ndim != 3:
        raise ValueError(f"X_k: calibrated residuals need the (H, W, 3) grid, got {X_k.shape}")
    H, W = X_k.shape[:2]
    X_f = as_points(X_f, "X_f", H * W)
    border = PIXEL_BORDER if cfg is None else cfg.pixel_border
    z_eps = Z_EPS if cfg is None else cfg.depth_eps
    zk = X_k[..., 2].reshape(-1)
    valid_meas = zk > z_eps
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    meas = np.stack([u.reshape(-1), v.reshape(-1), np.log(np.where(valid_meas, zk, 1.0))], -1)
    meas[~valid_meas] = 0.0
    P, dP = sim3.act_and_jacobian(T_CkCf, X_f)
    pz, dpz, valid_proj = project_calib_and_jacobian(P, K, (H, W), border, z_eps)
    valid = valid_meas & valid_proj
    r = np.where(valid[:, None], meas - pz, 0.0)
    J = np.where(valid[:, None, None], -(dpz @ dP), 0.0)
    return r, J, valid


def point_residual_and_jacobian(
    T_CkCf: FloatArray, X_f: FloatArray, X_k: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """3-D point residual (upstream's unused ablation kernel) and its Jacobian.

    Paper: Table 6 (point-error ablation). Upstream: gn_kernels.cu::point_align_kernel
    (there ``e = P - Xi`` with sigma_point = 0.05; here the tracking sign convention).

        r_n = Xk_n - T_CkCf · Xf_n,    J_n = -[I | -[P]x | P]

    Args:
        T_CkCf: (8,) Sim(3).
        X_f: (N, 3) or (H, W, 3) frame points in camera f.
        X_k: (N, 3) or (H, W, 3) keyframe points in camera k.

    Returns:
        r: (N, 3); J: (N, 3, 7).
    """
    X_k = as_points(X_k, "X_k")
    X_f = as_points(X_f, "X_f", len(X_k))
    P, dP = sim3.act_and_jacobian(T_CkCf, X_f)
    return X_k - P, -dP
