"""Bundle adjustment — the two camera models: g2o pinhole/stereo on SE(3), and BAL cameras.

**Pinhole (g2o ``EdgeSE3ProjectXYZ`` / ``EdgeStereoSE3ProjectXYZ``).** A pose ``T = [t, q]``
maps world to camera, ``Xc = R Xw + t = (X, Y, Z)``; each pose carries ``(fx, fy, cx, cy, bf)``:

    u = fx X/Z + cx,   v = fy Y/Z + cy,   ur = u - bf/Z        (stereo adds ur)

The residual is ``r = projection - measurement`` (3 rows; the third is 0 for mono edges). The
Jacobians returned here are ``dr/dx`` for the pose's left increment ``[omega, upsilon]`` and the
additive point increment. They are the negatives of g2o's closed forms (g2o differentiates
``measurement - projection``); the signs cancel in the normal equations.

**BAL (Snavely's Bundler model).** A camera is ``[w (3), t (3), f, k1, k2]``:

    P = R(w) X + t,  p = -P_xy / P_z,  d = 1 + k1 |p|^2 + k2 |p|^4,  pixel = f d p
    r = pixel - observed

Increments: the rotation is updated on the left, ``R <- exp(delta) R`` (so ``dP/d delta =
-[R X]x``), the other 6 entries additively; a camera block therefore has 9 DoF.

Public functions, in reading order:
    pinhole_residuals, pinhole_linearize, bal_residuals, bal_linearize, bal_retract_cameras

Shapes: M cameras, P points, O observations.

Upstream: g2o types/sba/types_six_dof_expmap.cpp (EdgeSE3ProjectXYZ::linearizeOplus,
EdgeStereoSE3ProjectXYZ::linearizeOplus); cuda-bundle-adjustment src/cuda_block_solver.cu
(computeActiveErrors / constructQuadraticForm kernels); Ceres examples/snavely_reprojection_error.h
(the BAL model, written here from its formula in the BAL paper).
"""

from __future__ import annotations

import numpy as np

from mslam_ref import so3
from mslam_ref.conventions import FloatArray, IntArray

__all__ = [
    "bal_linearize",
    "bal_residuals",
    "bal_retract_cameras",
    "pinhole_linearize",
    "pinhole_residuals",
]


def _pinhole_proj(
    poses: FloatArray,
    intrinsics: FloatArray,
    points: FloatArray,
    obs_cam: IntArray,
    obs_pt: IntArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Camera-frame points Xc (O,3), per-edge intrinsics (O,5), rotations (O,4) and proj (O,3)."""
    T = poses[obs_cam]
    Xc = so3.act(T[:, 3:], points[obs_pt]) + T[:, :3]
    K = intrinsics[obs_cam]
    iz = 1.0 / Xc[:, 2]
    u = K[:, 0] * Xc[:, 0] * iz + K[:, 2]
    v = K[:, 1] * Xc[:, 1] * iz + K[:, 3]
    proj = np.stack([u, v, u - K[:, 4] * iz], axis=-1)
    return Xc, K, T[:, 3:], proj


def pinhole_residuals(
    poses: FloatArray, intrinsics: FloatArray, points: FloatArray,
    obs_cam: IntArray, obs_pt: IntArray, meas: FloatArray, is_stereo: FloatArray,
) -> FloatArray:  # fmt: skip
    """Residuals ``projection - measurement`` of mono and stereo edges.

    Upstream: cuda_block_solver.cu (computeActiveErrors), g2o EdgeSE3ProjectXYZ::computeError.

    Args:
        poses: (M, 7) ``[t, q_xyzw]``, world to camera.
        intrinsics: (M, 5) ``(fx, fy, cx, cy, bf)``.
        points: (P, 3) world points.
        obs_cam: (O,) int camera index per edge.
        obs_pt: (O,) int point index per edge.
        meas: (O, 3) ``(u, v, ur)``; ``ur`` is ignored for mono edges.
        is_stereo: (O,) 1.0 for stereo edges, 0.0 for mono.

    Returns:
        (O, 3) residuals; the third entry is 0 for mono edges.
    """
    _, _, _, proj = _pinhole_proj(poses, intrinsics, points, obs_cam, obs_pt)
    r = proj - meas
    r[:, 2] *= is_stereo
    return r


def pinhole_linearize(
    poses: FloatArray, intrinsics: FloatArray, points: FloatArray,
    obs_cam: IntArray, obs_pt: IntArray, meas: FloatArray, is_stereo: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """Residuals and their Jacobians for the pose (left increment) and the point.

    Upstream: g2o types_six_dof_expmap.cpp::EdgeSE3ProjectXYZ::linearizeOplus and
    EdgeStereoSE3ProjectXYZ::linearizeOplus (negated: here J = dr/dx).

        dproj/dXc = [[fx/Z, 0, -fx X/Z^2], [0, fy/Z, -fy Y/Z^2], [fx/Z, 0, -fx X/Z^2 + bf/Z^2]]
        J_pose  = dproj/dXc [-[Xc]x, I]      J_point = dproj/dXc R

    Args:
        As :func:`pinhole_residuals`.

    Returns:
        r (O, 3), J_cam (O, 3, 6), J_pt (O, 3, 3); the third rows are 0 for mono edges.
    """
    Xc, K, q, proj = _pinhole_proj(poses, intrinsics, points, obs_cam, obs_pt)
    r = proj - meas
    iz = 1.0 / Xc[:, 2]
    O = Xc.shape[0]
    D = np.zeros((O, 3, 3))
    D[:, 0, 0] = K[:, 0] * iz
    D[:, 0, 2] = -K[:, 0] * Xc[:, 0] * iz * iz
    D[:, 1, 1] = K[:, 1] * iz
    D[:, 1, 2] = -K[:, 1] * Xc[:, 1] * iz * iz
    D[:, 2] = D[:, 0]
    D[:, 2, 2] += K[:, 4] * iz * iz
    D[:, 2] *= is_stereo[:, None]
    r[:, 2] *= is_stereo
    dXc = np.concatenate([-so3.hat(Xc), np.broadcast_to(np.eye(3), (O, 3, 3))], axis=-1)
    return r, D @ dXc, D @ so3.to_matrix(q)


def _bal_terms(cameras: FloatArray, points: FloatArray, obs_cam: IntArray, obs_pt: IntArray):
    C = cameras[obs_cam]
    R = so3.to_matrix(so3.exp(C[:, :3]))
    RX = np.einsum("oij,oj->oi", R, points[obs_pt])
    P = RX + C[:, 3:6]
    p = -P[:, :2] / P[:, 2:3]
    r2 = np.sum(p * p, axis=-1)
    d = 1.0 + C[:, 7] * r2 + C[:, 8] * r2 * r2
    return C, R, RX, P, p, r2, d


def bal_residuals(
    cameras: FloatArray,
    points: FloatArray,
    obs_cam: IntArray,
    obs_pt: IntArray,
    obs: FloatArray,
) -> FloatArray:
    """BAL reprojection residuals ``f d(p) p - observed`` with ``p = -P_xy / P_z``.

    Upstream: the BAL camera model (grail.cs.washington.edu/projects/bal), Ceres
    examples/snavely_reprojection_error.h::SnavelyReprojectionError.

    Args:
        cameras: (M, 9) ``[w, t, f, k1, k2]``.
        points: (P, 3).
        obs_cam: (O,) int.
        obs_pt: (O,) int.
        obs: (O, 2) observed pixels (origin at the image centre, y up).

    Returns:
        (O, 2) residuals.
    """
    C, _, _, _, p, _, d = _bal_terms(cameras, points, obs_cam, obs_pt)
    return (C[:, 6] * d)[:, None] * p - obs


def bal_linearize(
    cameras: FloatArray,
    points: FloatArray,
    obs_cam: IntArray,
    obs_pt: IntArray,
    obs: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """BAL residuals and Jacobians for ``[delta_rot (left), dt, df, dk1, dk2]`` and the point.

        dpix/dp = f (d I + 2 (k1 + 2 k2 |p|^2) p p^T)
        dp/dP   = [[-1/Pz, 0, Px/Pz^2], [0, -1/Pz, Py/Pz^2]]
        dP/d delta = -[R X]x,  dP/dt = I,  dP/dX = R
        dpix/df = d p,  dpix/dk1 = f |p|^2 p,  dpix/dk2 = f |p|^4 p

    Args:
        As :func:`bal_residuals`.

    Returns:
        r (O, 2), J_cam (O, 2, 9), J_pt (O, 2, 3).
    """
    C, R, RX, P, p, r2, d = _bal_terms(cameras, points, obs_cam, obs_pt)
    f, k1, k2 = C[:, 6], C[:, 7], C[:, 8]
    r = (f * d)[:, None] * p - obs
    O = C.shape[0]
    outer = p[:, :, None] * p[:, None, :]
    dpix_dp = (f * d)[:, None, None] * np.eye(2) + (2.0 * f * (k1 + 2.0 * k2 * r2))[
        :, None, None
    ] * outer
    iz = 1.0 / P[:, 2]
    dp_dP = np.zeros((O, 2, 3))
    dp_dP[:, 0, 0] = -iz
    dp_dP[:, 1, 1] = -iz
    dp_dP[:, :, 2] = P[:, :2] * (iz * iz)[:, None]
    A = dpix_dp @ dp_dP  # (O, 2, 3) dpix/dP
    Jc = np.empty((O, 2, 9))
    Jc[:, :, 0:3] = A @ (-so3.hat(RX))
    Jc[:, :, 3:6] = A
    Jc[:, :, 6] = d[:, None] * p
    Jc[:, :, 7] = (f * r2)[:, None] * p
    Jc[:, :, 8] = (f * r2 * r2)[:, None] * p
    return r, Jc, A @ R


def bal_retract_cameras(cameras: FloatArray, delta: FloatArray) -> FloatArray:
    """Apply 9-DoF increments to BAL cameras: ``R <- exp(delta_rot) R``, the rest additive.

    Args:
        cameras: (M, 9).
        delta: (M, 9) ``[delta_rot, dt, df, dk1, dk2]``.

    Returns:
        (M, 9) new cameras (rotation stored back as an angle-axis vector, ``|w| <= pi``).
    """
    q = so3.mul(so3.exp(delta[:, :3]), so3.exp(cameras[:, :3]))
    out = cameras + delta
    out[:, :3] = so3.log(q)
    return out
