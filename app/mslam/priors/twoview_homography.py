"""The best homography of an image pair: how far its flow is from a pure rotation, and that rotation.

A pair's flow is a homography ``u_j ~ H u_i`` for a pure rotation (``K⁻¹ H K = R``), for a tiny
baseline, and for a plane seen from two centres (``K⁻¹ H K = R + t nᵀ/d``). The first two have
no parallax: their depths cannot be triangulated. :func:`homography_parallax` measures the
parallax of a pair in pixels, two terms, the larger is returned:

* off-homography parallax: 90th percentile of ``‖u_j - H u_i‖`` (a scene that is not a plane);
* plane parallax: ``f · (σ₁ - σ₃) / σ₂ - plane_margin_px`` with σ the singular values of
  ``K⁻¹ H K``, which are equal for a rotation and differ by about ``‖t‖/d`` for a plane at
  distance d. H fitted to DIS flow is noisy at the image borders: a pure 3° rotation at
  128x96 gives ``f · (σ₁ - σ₃) / σ₂ ≈ 0.6 px``, hence the margin.

**Uncalibrated pairs** (``focal_free``). The plane term depends on K: a pure rotation seen
through a focal length that is not the camera's is not a rotation of ``K⁻¹ H K`` (the 60°
guess for a 70° camera gives a median plane term of 1.7 px for the one-frame pairs of
``synthetic:rotation:60`` at 96x72 with the full-resolution flow, 2026-11-27). With
``focal_free`` the plane term is the smallest over focal lengths ``f`` from
:data:`FOCAL_SPAN` times K's (``K_f`` with K's principal point): a pair is a rotation when it
is one for *some* camera. A plane does not pass for a rotation: a fronto-parallel plane
approached head-on scales the image (σ₃ grows with ``‖t‖/d`` at every f), one passed
sideways shifts it by ``Δ`` pixels, a plane term of about ``Δ`` at every f.

:func:`homography_rotation` gives the rotation of such a pair, the rotation nearest to
``K_f⁻¹ H K_f`` (the focal length that made the pair most like a rotation).

Public names, in reading order:
    FOCAL_SPAN, HomographyFit, fit_homography, homography_fit, homography_parallax,
    homography_rotation
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mslam_ref.conventions import FloatArray

__all__ = [
    "FOCAL_SPAN",
    "HomographyFit",
    "fit_homography",
    "homography_fit",
    "homography_parallax",
    "homography_rotation",
]

#: Focal lengths tried by the focal-free plane term, as factors of the guess: fields of view
#: from 43° (a narrow webcam) to 88° across the long side around the 60° guess (55 steps,
#: 1.6 % apart). Longer focal lengths are left out: the longer the lens, the more a sideways
#: step in front of a wall looks like a turn (8 cm at 2 m with a 1° turn: a plane term of
#: 3.7 px at the guess, 2.6 px at 1.2 times it, 2.1 px at 1.4 times, 2.9 px at 1.6 times).
FOCAL_SPAN = np.geomspace(0.6, 1.45, 55)


@dataclass(frozen=True)
class HomographyFit:
    """A pair's best homography, measured (module docstring).

    Attributes:
        H: (3, 3) the homography ``u_j ~ H u_i``, or None when none could be fitted.
        parallax_px: the larger of the off-homography and plane terms, pixels (0 without H).
        focal_px: the focal length at which the plane term was measured (K's, or the
            smallest term's with ``focal_free``).
    """

    H: FloatArray | None
    parallax_px: float
    focal_px: float


def fit_homography(uv_i: FloatArray, uv_j: FloatArray, ransac_px: float) -> FloatArray | None:
    """RANSAC homography ``u_j ~ H u_i`` of (N, 2) correspondences; None when N < 4 or the fit
    fails."""
    if len(uv_i) < 4:
        return None
    try:
        H, _ = cv2.findHomography(uv_i, uv_j, cv2.RANSAC, ransac_px)
    except cv2.error:
        return None
    if H is None or not np.all(np.isfinite(H)):
        return None
    return np.asarray(H, np.float64)


def _with_focal(K: FloatArray, f: float) -> FloatArray:
    K_f = np.asarray(K, np.float64).copy()
    K_f[0, 0] = K_f[1, 1] = f
    return K_f


def _plane_px(H: FloatArray, K: FloatArray) -> float:
    """``f · (σ₁ - σ₃) / σ₂`` of ``K⁻¹ H K`` (f the mean focal length of K)."""
    sv = np.linalg.svd(np.linalg.inv(K) @ H @ K, compute_uv=False)
    return float(0.5 * (K[0, 0] + K[1, 1]) * (sv[0] - sv[2]) / max(sv[1], 1e-12))


def homography_fit(
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    ransac_px: float = 1.0,
    plane_margin_px: float = 1.0,
    focal_free: bool = False,
) -> HomographyFit:
    """The pair's homography and parallax (module docstring).

    Args:
        uv_i, uv_j: (N, 2) corresponding pixels (N >= 4; fewer gives no H).
        K: (3, 3) intrinsics (the focal-length guess when uncalibrated).
        ransac_px: RANSAC threshold of the homography (pixels).
        plane_margin_px: subtracted from the plane term.
        focal_free: the plane term is the smallest over focal lengths ``FOCAL_SPAN · f``.
    """
    uv_i = np.ascontiguousarray(uv_i, dtype=np.float64).reshape(-1, 2)
    uv_j = np.ascontiguousarray(uv_j, dtype=np.float64).reshape(-1, 2)
    f0 = 0.5 * float(K[0, 0] + K[1, 1])
    H = fit_homography(uv_i, uv_j, ransac_px)
    if H is None:
        return HomographyFit(None, 0.0, f0)
    p = np.hstack([uv_i, np.ones((len(uv_i), 1))]) @ H.T
    w = np.where(np.abs(p[:, 2:]) > 1e-12, p[:, 2:], 1e-12)
    off_plane = float(np.percentile(np.linalg.norm(p[:, :2] / w - uv_j, axis=1), 90))
    if not focal_free:
        return HomographyFit(H, max(off_plane, _plane_px(H, K) - plane_margin_px), f0)
    focals = f0 * FOCAL_SPAN
    planes = [_plane_px(H, _with_focal(K, f)) for f in focals]
    best = int(np.argmin(planes))
    return HomographyFit(H, max(off_plane, planes[best] - plane_margin_px), float(focals[best]))


def homography_parallax(
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    ransac_px: float = 1.0,
    plane_margin_px: float = 1.0,
    focal_free: bool = False,
) -> float:
    """Parallax of a pair in pixels: how far the flow is from a pure rotation
    (:func:`homography_fit`'s ``parallax_px``; module docstring)."""
    return homography_fit(uv_i, uv_j, K, ransac_px, plane_margin_px, focal_free).parallax_px


def homography_rotation(H: FloatArray, K: FloatArray, focal_px: float | None = None) -> FloatArray:
    """The rotation ``R_ji`` (3, 3) nearest to ``K_f⁻¹ H K_f`` (``K_f``: K with focal length
    ``focal_px``, else K): the rotation of a pair whose flow is a rotation, ``x_j ~ R_ji x_i``."""
    K_f = np.asarray(K, np.float64) if focal_px is None else _with_focal(K, focal_px)
    M = np.linalg.inv(K_f) @ np.asarray(H, np.float64) @ K_f
    M = M / np.cbrt(np.linalg.det(M))  # H is known up to scale and sign
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R
