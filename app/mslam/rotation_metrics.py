"""Orientation errors of a trajectory, beside the ATE (which compares positions only).

A trajectory can place its cameras well and still turn them wrongly: its positions give a small
ATE while every keyframe's pointmap is rotated, which smears the map. Over the associated pose
pairs, for pairs (i, j) about ``lag_s`` seconds apart:

* the **relative rotation error**: ``angle((R_est,iᵀ R_est,j)ᵀ (R_gt,iᵀ R_gt,j))`` in degrees
  (evo's ``evo_rpe --pose_relation angle_deg`` over that lag), its median and maximum. Unlike
  an orientation error after the ATE's alignment it needs no alignment: on a short, nearly
  straight path the positions leave the rotation about the path free (docs/evaluation.md), and
  that freedom, not the estimate, would dominate;
* the **rotation gain**: the world-frame turns ``ω_gt = log(R_gt,j R_gt,iᵀ)`` and
  ``ω_est = log(R_est,j R_est,iᵀ)``, the rotation ``Q`` that best maps the ω_est onto the ω_gt
  (Procrustes; it takes up the estimate's own world frame and cannot change a length), and
  ``gain = Σ (Q ω_est)·ω_gt / Σ |ω_gt|²``. 1 when the estimate turns as much as the camera did,
  0.85 when it turns 15 % too little. Noise in ``ω_est`` averages out of the dot product, where
  a ratio of summed angles would grow with it. None when the camera hardly turned
  (``Σ |ω_gt|`` under :data:`MIN_TURN_DEG`).

Public names, in reading order:
    MIN_TURN_DEG, rotations, angle_deg, lagged_turns, rotation_gain, rotation_report,
    associated_report
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_ref import so3
from mslam_ref.conventions import FloatArray

__all__ = [
    "MIN_TURN_DEG",
    "angle_deg",
    "associated_report",
    "lagged_turns",
    "rotation_gain",
    "rotation_report",
    "rotations",
]

#: Total ground-truth turn (degrees, summed over the lagged pairs) under which no gain is given.
MIN_TURN_DEG = 5.0


def rotations(poses: Any) -> FloatArray | None:
    """(n, 3, 3) rotation matrices of (n, 7) ``[t, q_xyzw]`` or (n, 8) Sim(3) poses, or of
    (n, 4, 4) / (n, 3, 4) matrices (projected to the nearest rotation); None for (n, 3)
    positions, which carry no orientation."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim == 2 and arr.shape[1] in (7, 8):
        q = arr[:, 3:7] / np.linalg.norm(arr[:, 3:7], axis=1, keepdims=True)
        return np.asarray(so3.to_matrix(q))
    if arr.ndim == 3 and arr.shape[1:] in ((4, 4), (3, 4)):
        U, _, Vt = np.linalg.svd(arr[:, :3, :3])
        d = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= d[:, None]
        return U @ Vt
    return None


def angle_deg(R: FloatArray) -> FloatArray:
    """(...) rotation angles in degrees of (..., 3, 3) rotations: ``atan2(sin θ, cos θ)`` with
    ``cos θ = (tr R - 1) / 2`` and ``sin θ`` the length of R's antisymmetric part's vector
    (``arccos`` alone loses half the digits near 0°: 2e-6° for an exact identity)."""
    R = np.asarray(R, np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], -1) / 2.0  # fmt: skip
    return np.degrees(np.arctan2(np.linalg.norm(v, axis=-1), c))


def _log(R: FloatArray) -> FloatArray:
    """(n, 3) rotation vectors of (n, 3, 3) rotations."""
    return np.asarray(so3.log(so3.from_matrix(R)))


def _lag(stamps: FloatArray | None, n: int, lag_s: float, lag_pairs: int) -> int:
    """Pairs apart that make ``lag_s`` seconds (``lag_pairs`` without stamps), at most n - 1."""
    lag = lag_pairs
    if stamps is not None and n > 1:
        dt = float(np.median(np.diff(stamps)))
        lag = max(1, round(lag_s / dt)) if dt > 0 else lag_pairs
    return min(lag, n - 1)


def lagged_turns(
    R_est: FloatArray, R_gt: FloatArray, lag: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For pairs ``lag`` apart: world-frame turns ω_est, ω_gt (m, 3) and the relative rotation
    errors (m,) in degrees; inputs (n, 3, 3), ``1 <= lag < n``."""
    w_gt = _log(np.einsum("nij,nkj->nik", R_gt[lag:], R_gt[:-lag]))
    w_est = _log(np.einsum("nij,nkj->nik", R_est[lag:], R_est[:-lag]))
    rel_est = np.einsum("nji,njk->nik", R_est[:-lag], R_est[lag:])
    rel_gt = np.einsum("nji,njk->nik", R_gt[:-lag], R_gt[lag:])
    return w_est, w_gt, angle_deg(np.einsum("nji,njk->nik", rel_est, rel_gt))


def rotation_gain(w_est: FloatArray, w_gt: FloatArray) -> float | None:
    """``Σ (Q ω_est)·ω_gt / Σ |ω_gt|²`` with Q the best rotation (Procrustes) of (m, 3) turns;
    None when the true turns sum to less than :data:`MIN_TURN_DEG`."""
    if np.degrees(np.linalg.norm(w_gt, axis=1).sum()) < MIN_TURN_DEG:
        return None
    U, _, Vt = np.linalg.svd(w_gt.T @ w_est)
    Q = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return float(np.sum((w_est @ Q.T) * w_gt) / np.sum(w_gt * w_gt))


def rotation_report(
    stamps: Any, est_poses: Any, gt_poses: Any, lag_s: float = 0.5, lag_pairs: int = 15
) -> dict[str, float | None] | None:
    """The figures for associated poses (pair k: ``est_poses[k]`` and ``gt_poses[k]``), or None
    when either side has positions only or there are fewer than two pairs.

    Args:
        stamps: (n,) stamps of the pairs, or None (then pairs are ``lag_pairs`` apart).
        est_poses, gt_poses: (n, ...) poses as :func:`rotations` takes them.
        lag_s: seconds between the two poses of a pair.

    Returns:
        ``rotation_lag_s`` (the lag used; None without stamps), ``rotation_error_median_deg``,
        ``rotation_error_max_deg``, ``rotation_gain``.
    """
    R_est, R_gt = rotations(est_poses), rotations(gt_poses)
    if R_est is None or R_gt is None or len(R_est) != len(R_gt):
        return None
    st = None if stamps is None else np.asarray(stamps, np.float64)
    lag = _lag(st, len(R_est), lag_s, lag_pairs)
    if lag < 1:
        return None
    w_est, w_gt, err = lagged_turns(R_est, R_gt, lag)
    return {
        "rotation_lag_s": None if st is None else float(st[lag] - st[0]),
        "rotation_error_median_deg": float(np.median(err)),
        "rotation_error_max_deg": float(np.max(err)),
        "rotation_gain": rotation_gain(w_est, w_gt),
    }


def associated_report(
    est_stamps: Any, est_poses: Any, gt_stamps: Any, gt_poses: Any, max_diff: float = 0.01
) -> dict[str, float | None] | None:
    """:func:`rotation_report` of the pairs evo's association finds (as the ATE's,
    :func:`mslam.evaluate.associate`); works where the ATE cannot align (a camera that only
    turns). None, never an exception, when the stamps cannot be associated: a run's outputs
    do not depend on it."""
    from mslam.evaluate import associate

    try:
        i_est, i_gt = associate(est_stamps, gt_stamps, max_diff)
    except ValueError:
        return None
    st = np.asarray(est_stamps, np.float64)[i_est]
    return rotation_report(st, np.asarray(est_poses)[i_est], np.asarray(gt_poses)[i_gt])
