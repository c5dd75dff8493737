"""Keyframe scale consensus for the exported map: each keyframe's depth against the others'.

A keyframe's map points are ``T_WC · X`` (its Sim(3) pose applied to its fused pointmap). With
a monocular prior every pair has its own scale; tracking and the backend bring the pointmaps to
one scale through the poses, but a keyframe whose pointmap's scale and pose's scale disagree
puts its whole cloud too far from, or too close to, its camera. The other keyframes see the
same surfaces, so the disagreement is measurable without ground truth:

* every keyframe ``a``'s exported points are moved into each other keyframe ``b``'s camera
  (``T_WC[b]⁻¹ · T_WC[a] · X_a``) and projected with ``b``'s pinhole, fitted to its own
  pointmap (``u = f_x x/z + c_x``, ``v = f_y y/z + c_y``, least squares);
* where at least ``min_pixels`` of them (thinned to ``max_points``) land on exported pixels of ``b``, the median of
  ``log(‖X_a in b‖ / ‖X_b‖)`` is the pair's log-range ratio;
* ``m_a``, the median over the keyframes that overlap ``a``, is positive when ``a``'s points
  lie farther than the others put the same surfaces.

:func:`scale_corrections` turns ``|m_a| > tolerance`` into a factor ``exp(-m_a)`` on ``X_a``
(its points scaled about its camera centre); smaller disagreements stay (they are the per-pair
depth distortion, which rescaling does not fix). Measured 2026-11-26 on the 7-Scenes kitchen
clip, RGB only (docs/evaluation.md, section 4.2).

Public names, in reading order:
    pinhole_fit, keyframe_scale_disagreement, scale_corrections
"""

from __future__ import annotations

import numpy as np

from mslam_ref import sim3
from mslam_ref.conventions import FloatArray

__all__ = ["keyframe_scale_disagreement", "pinhole_fit", "scale_corrections"]


def pinhole_fit(X: FloatArray, valid: np.ndarray | None = None) -> FloatArray:
    """``(f_x, f_y, c_x, c_y)`` of the pinhole that projects pointmap ``X`` (H, W, 3) onto its
    own pixel grid, fitted by least squares on the ``valid`` (H, W) pixels (default: all) with
    ``z > 0``. Exact for a pointmap back-projected through a pinhole (the two-view prior's),
    the closest pinhole otherwise.

    Raises:
        ValueError: fewer than two such pixels.
    """
    H, W = X.shape[:2]
    v, u = np.mgrid[:H, :W]
    ok = X[..., 2] > 0 if valid is None else valid & (X[..., 2] > 0)
    if ok.sum() < 2:
        raise ValueError("X: fewer than two points in front of the camera")
    z = X[..., 2][ok]
    out = []
    for coord, pix in ((X[..., 0][ok] / z, u[ok]), (X[..., 1][ok] / z, v[ok])):
        A = np.stack([coord, np.ones_like(coord)], -1)
        out.append(np.linalg.lstsq(A, pix.astype(np.float64), rcond=None)[0])
    return np.array([out[0][0], out[1][0], out[0][1], out[1][1]])


def keyframe_scale_disagreement(
    X: FloatArray,
    C: FloatArray,
    T_WC: FloatArray,
    c_thresh: float,
    min_pixels: int = 200,
    max_points: int = 2000,
) -> FloatArray:
    """``m`` (K,): each keyframe's median log-range ratio against the keyframes it overlaps.

    Args:
        X: (K, H, W, 3) keyframe pointmaps; C: (K, H, W) average confidences ``C/N``;
        T_WC: (K, 8) Sim(3) poses; c_thresh: only pixels with ``C > c_thresh`` take part
            (the export's threshold); min_pixels: overlap needed for a pair to count;
            max_points: each keyframe's points are thinned to about this many (a regular
            stride), which bounds the cost at ``K² · max_points`` projections.

    Returns:
        (K,) float64, 0 for a keyframe that overlaps no other.
    """
    n, H, W = C.shape
    keep = (C > c_thresh) & (X[..., 2] > 0)
    cams = [pinhole_fit(X[b], keep[b]) if keep[b].sum() >= 3 else None for b in range(n)]
    m = np.zeros(n)
    for a in range(n):
        P_a = X[a][keep[a]]
        P_w = sim3.act(T_WC[a], P_a[:: max(1, len(P_a) // max_points)])
        ratios = []
        for b in range(n):
            cam = cams[b]
            if b == a or cam is None or len(P_w) < min_pixels:
                continue
            P = sim3.act(sim3.inv(T_WC[b]), P_w)
            fx, fy, cx, cy = cam
            z = np.where(P[:, 2] > 0, P[:, 2], 1.0)
            u = np.rint(fx * P[:, 0] / z + cx).astype(np.int64)
            v = np.rint(fy * P[:, 1] / z + cy).astype(np.int64)
            on = (P[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            on[on] = keep[b][v[on], u[on]]
            if on.sum() < min_pixels:
                continue
            r_b = np.linalg.norm(X[b][v[on], u[on]], axis=-1)
            ratios.append(float(np.median(np.log(np.linalg.norm(P[on], axis=-1) / r_b))))
        m[a] = float(np.median(ratios)) if ratios else 0.0
    return m


def scale_corrections(
    X: FloatArray, C: FloatArray, T_WC: FloatArray, c_thresh: float, tolerance: float
) -> FloatArray:
    """Factors (K,) for the keyframe pointmaps: ``exp(-m)`` where ``|m| > tolerance``, else 1,
    with ``m`` from :func:`keyframe_scale_disagreement` (same arguments). ``tolerance <= 0``
    (the check is off) or fewer than 3 keyframes (no majority) give ones."""
    n = len(X)
    if tolerance <= 0 or n < 3:
        return np.ones(n)
    m = keyframe_scale_disagreement(X, C, T_WC, c_thresh)
    return np.where(np.abs(m) > tolerance, np.exp(-m), 1.0)
