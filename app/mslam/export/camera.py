"""The pinhole camera the exports use: the given intrinsics, or one estimated from the pointmaps.

In calibrated mode the run's intrinsics are known (``SlamSystem.K``, at the pointmap
resolution). Otherwise the prior's pointmaps imply a camera: a point ``X = (x, y, z)`` of a
canonical pointmap seen at pixel ``(u, v)`` satisfies ``u - cx = f x / z`` and
``v - cy = f y / z``. With the principal point at the image centre (pixel-centre convention,
``cx = (W - 1) / 2``) and square pixels, the confidence-weighted least-squares focal length is

    f = sum_n w_n (a_n · d_n) / sum_n w_n |a_n|^2,   a_n = (x/z, y/z),  d_n = (u - cx, v - cy)

over the confident pixels (``C / N > c_thresh``, ``z > 0``) of every keyframe.

Public names, in reading order:
    focal_from_pointmap, run_intrinsics
"""

from __future__ import annotations

import numpy as np

from mslam.system.frontend import SlamSystem
from mslam_ref.conventions import FloatArray

__all__ = ["focal_from_pointmap", "run_intrinsics"]

#: Average-confidence threshold of the pixels that take part (the PLY's, docs/upstream.md §13).
C_CONF_THRESHOLD = 1.5


def focal_from_pointmap(
    X: FloatArray, C: FloatArray, c_thresh: float = C_CONF_THRESHOLD
) -> FloatArray:
    """Pinhole intrinsics implied by canonical pointmaps (principal point at the centre).

    Args:
        X: (K, H, W, 3) or (H, W, 3) canonical pointmaps, each in its own camera.
        C: (K, H, W) or (H, W) average confidences.
        c_thresh: pixels with ``C > c_thresh`` take part (all finite ones when none passes).

    Returns:
        (3, 3) float64 ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]``.

    Raises:
        ValueError: when no pixel has a finite point in front of the camera.
    """
    X = np.asarray(X, np.float64)
    C = np.asarray(C, np.float64)
    if X.ndim == 3:
        X, C = X[None], C[None]
    _, H, W, _ = X.shape
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    u, v = np.meshgrid(np.arange(W) - cx, np.arange(H) - cy)
    z = X[..., 2]
    ok = np.all(np.isfinite(X), axis=-1) & (z > 1e-9)
    keep = ok & (C > c_thresh) if np.any(ok & (C > c_thresh)) else ok
    if not np.any(keep):
        raise ValueError("X: no finite point in front of the camera to estimate a focal length")
    zs = np.where(keep, z, 1.0)
    ax, ay = X[..., 0] / zs, X[..., 1] / zs
    w = np.where(keep, np.maximum(C, 1e-6), 0.0)
    num = np.sum(w * (ax * u[None] + ay * v[None]))
    den = np.sum(w * (ax * ax + ay * ay))
    if not den > 0:
        raise ValueError("X: all points on the optical axis; the focal length is undetermined")
    f = float(num / den)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def run_intrinsics(system: SlamSystem) -> tuple[FloatArray, bool]:
    """The intrinsics at the pointmap resolution and whether they were given (calibrated mode).

    Returns:
        K (3, 3) float64 and ``True`` when given, ``False`` when estimated from the keyframes.
    """
    if system.K is not None:
        return np.asarray(system.K, np.float64), True
    from mslam_ref import fusion

    X, C = system.keyframes.pointmaps(fusion, None)
    return focal_from_pointmap(X, C), False
