"""Guided dense flow for the two-view prior — sparse features seed DIS beyond its range.

The two-view prior (:mod:`mslam.priors.twoview`) stands in for MASt3R's pairwise pointmaps
(paper §3, "Pointmap matching" and §3.4's loop-closure edges between keyframes far apart in
time). Its correspondences come from DIS optical flow, which is coarse-to-fine over a pyramid
whose coarsest level is fixed by the image size: at 160x120 there are three levels (1/4 is the
coarsest), so DIS follows motions of ~10-15 px only. Measured on the 240-frame synthetic loop
(160x120), the share of forward–backward consistent pixels of plain DIS falls from 0.70 at 6
frames apart (~11° of rotation) to 0.01 at 9 frames (~15°): with plain DIS every pair beyond
that — most retrieval candidates, and every loop-closure candidate — is degenerate
(``few_inliers``), and no loop closes however well retrieval ranks.

The remedy is the classical one (wide-baseline matching, then dense refinement): SIFT
keypoints matched by Lowe's ratio test and kept one-to-one give a RANSAC homography
``u_j ≈ H u_i``, and the flow ``H u - u`` initialises DIS, which then only has to recover the
residual parallax of the scene's depth relative to that plane. :func:`guided_flow` keeps
whichever of the plain and the guided flow has more forward–backward consistent pixels, so
small-motion pairs (where plain DIS is already right) are unaffected unless the guided flow is
more consistent — except that a flow must reproduce the sparse matches it is chosen over:
plain DIS that reproduces fewer than ``min_agreement`` of the homography's inlier matches
(within ``ransac_px``, :func:`match_agreement`) while the guided flow reproduces at least that
share has locked onto a wrong motion, however self-consistent. Measured on
``synthetic:rotation:60`` at 96x72 (frames 40 and 32, 34° apart, 2026-11-26): plain DIS had a
consistent share of 0.394 against the guided flow's 0.387, and reproduced none of the 177
homography inliers (median error 39 px) where the guided flow reproduced all (0.4 px); the
pair's essential matrix from the plain flow was 49° off in rotation and still passed as a pair
with parallax.

Public names, in reading order:
    GuideConfig, sift_keypoints, sparse_matches, homography_flow, consistent_share,
    match_agreement, guided_flow
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mslam.priors.keypoints import ratio_matches
from mslam.priors.twoview_dis import _grey, dense_flow
from mslam.priors.twoview_geometry import forward_backward_error
from mslam_ref.conventions import FloatArray

__all__ = [
    "GuideConfig",
    "consistent_share",
    "guided_flow",
    "homography_flow",
    "match_agreement",
    "sift_keypoints",
    "sparse_matches",
]


@dataclass(frozen=True)
class GuideConfig:
    """Sparse-feature guidance of the dense flow (module docstring).

    Attributes:
        enabled: False reproduces plain DIS (the first version of the prior).
        n_features: SIFT keypoints per image (strongest responses).
        contrast_threshold: SIFT contrast threshold; OpenCV's 0.04 is absolute in intensity
            and starves low-contrast images (as in the RGB-D prior, docs/priors.md).
        detect_min_width: images narrower than this are upscaled for detection only.
        ratio: Lowe ratio test.
        ransac_px: homography RANSAC threshold (pixels). The homography only has to bring
            DIS within its range, so a loose threshold that keeps the scene's parallax
            among the inliers is right.
        min_matches: fewer homography inliers and no guided flow is tried.
        skip_share: plain DIS with at least this consistent share is kept without trying
            the guided flow (on the 7-Scenes kitchen at 160x120 the guided flow of such pairs
            was at most 0.02 more consistent; skipping it saves two of the four DIS calls,
            the SIFT matching and the homography of most tracking pairs).
        min_agreement: share of the homography's inlier matches a flow must reproduce for
            plain DIS to be kept over a guided flow that does (module docstring).
    """

    enabled: bool = True
    n_features: int = 2000
    contrast_threshold: float = 0.01
    detect_min_width: int = 480
    ratio: float = 0.8
    ransac_px: float = 3.0
    min_matches: int = 20
    skip_share: float = 0.9
    min_agreement: float = 0.5

    def __post_init__(self) -> None:
        if self.n_features < 8 or self.min_matches < 4:
            raise ValueError("guide.n_features, guide.min_matches: must be >= 8 and >= 4")
        if not (0 < self.ratio <= 1 and self.ransac_px > 0 and self.contrast_threshold >= 0):
            raise ValueError("guide.ratio in (0, 1], guide.ransac_px > 0, contrast >= 0")


def sift_keypoints(rgb: np.ndarray, cfg: GuideConfig = GuideConfig()):
    """SIFT keypoints of one image: ``(uv (N, 2) pixels of the image, descriptors (N, 128))``.

    Detection runs on the grey image upscaled (cubic) to at least ``detect_min_width``;
    keypoint positions are mapped back to the image's pixels. Descriptors are None when
    nothing is detected.
    """
    grey = _grey(rgb)
    H, W = grey.shape
    f = max(1, int(np.ceil(cfg.detect_min_width / W)))
    if f > 1:
        grey = cv2.resize(grey, (W * f, H * f), interpolation=cv2.INTER_CUBIC)
    det = cv2.SIFT.create(nfeatures=cfg.n_features, contrastThreshold=cfg.contrast_threshold)
    kps, desc = det.detectAndCompute(grey, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2)), None
    return (np.array([k.pt for k in kps], dtype=np.float64) + 0.5) / f - 0.5, desc


def sparse_matches(kp_i, kp_j, ratio: float = 0.8) -> tuple[FloatArray, FloatArray]:
    """Ratio-test matches of i's keypoints in j, one-to-one: ``uv_i (M, 2), uv_j (M, 2)``.

    A keypoint of j claimed by several keypoints of i is ambiguous and dropped (on
    featureless regions one keypoint can attract dozens of matches).
    """
    (uv_i, d_i), (uv_j, d_j) = kp_i, kp_j
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    if d_i is None or d_j is None or len(uv_i) < 2 or len(uv_j) < 2:
        return empty
    qi, tj = ratio_matches(d_i, d_j, ratio)
    if len(qi) == 0:
        return empty
    _, inv, counts = np.unique(tj, return_inverse=True, return_counts=True)
    once = counts[inv] == 1
    return uv_i[qi[once]], uv_j[tj[once]]


def homography_flow(H_ij: FloatArray, height: int, width: int) -> FloatArray:
    """Flow ``F(u) = H u - u`` of a homography over the pixel grid: (H, W, 2) float32.

    Pixels whose homogeneous coordinate vanishes get zero flow.
    """
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    p = np.stack([u, v, np.ones_like(u)], -1) @ np.asarray(H_ij, dtype=np.float64).T
    w = p[..., 2:]
    ok = np.abs(w) > 1e-9
    F = np.where(ok, p[..., :2] / np.where(ok, w, 1.0) - np.stack([u, v], -1), 0.0)
    return F.astype(np.float32)


def consistent_share(F_ij: FloatArray, F_ji: FloatArray, fb_px: float) -> float:
    """Share of pixels of i whose forward–backward error is below ``fb_px``."""
    e, _ = forward_backward_error(F_ij, F_ji)
    return float(np.mean(e < fb_px))


def match_agreement(F_ij: FloatArray, uv_i: FloatArray, uv_j: FloatArray, tol_px: float) -> float:
    """Share of the matches ``uv_i -> uv_j`` (M, 2) that the flow ``F_ij`` (H, W, 2), read at
    the nearest pixel of ``uv_i``, reproduces within ``tol_px`` pixels (1 for no match)."""
    if len(uv_i) == 0:
        return 1.0
    h, w = F_ij.shape[:2]
    u = np.clip(np.rint(uv_i[:, 0]), 0, w - 1).astype(np.int64)
    v = np.clip(np.rint(uv_i[:, 1]), 0, h - 1).astype(np.int64)
    err = np.linalg.norm(uv_i + F_ij[v, u] - uv_j, axis=1)
    return float(np.mean(err < tol_px))


def guided_flow(
    rgb_i: np.ndarray,
    rgb_j: np.ndarray,
    kp_i,
    kp_j,
    fb_px: float = 1.0,
    cfg: GuideConfig = GuideConfig(),
) -> tuple[FloatArray, FloatArray, bool]:
    """Dense flow both ways, DIS plain or seeded by a sparse homography (module docstring).

    Args:
        rgb_i, rgb_j: (H, W, 3) uint8 images.
        kp_i, kp_j: :func:`sift_keypoints` of each image (computed once per image by the
            caller), or functions without arguments returning them (called only when needed).
        fb_px: forward–backward threshold of :func:`consistent_share`.
        cfg: guidance parameters.

    Returns:
        F_ij, F_ji: (H, W, 2) float64 flows; guided: whether the seeded flow was kept (when it
        has the larger consistent share, or when only it reproduces the sparse matches).
    """
    F_ij, F_ji = dense_flow(rgb_i, rgb_j)
    if not cfg.enabled:
        return F_ij, F_ji, False
    plain_share = consistent_share(F_ij, F_ji, fb_px)
    if plain_share >= cfg.skip_share:
        return F_ij, F_ji, False
    kp_i, kp_j = (kp() if callable(kp) else kp for kp in (kp_i, kp_j))
    uv_i, uv_j = sparse_matches(kp_i, kp_j, cfg.ratio)
    if len(uv_i) < cfg.min_matches:
        return F_ij, F_ji, False
    try:
        H_ij, mask = cv2.findHomography(uv_i, uv_j, cv2.RANSAC, cfg.ransac_px)
    except cv2.error:
        return F_ij, F_ji, False
    if H_ij is None or mask is None or int(mask.sum()) < cfg.min_matches:
        return F_ij, F_ji, False
    if not np.all(np.isfinite(H_ij)) or abs(np.linalg.det(H_ij)) < 1e-9:
        return F_ij, F_ji, False
    h, w = F_ij.shape[:2]
    H, H_inv = np.asarray(H_ij, np.float64), np.asarray(np.linalg.inv(H_ij), np.float64)
    G_ij, G_ji = dense_flow(rgb_i, rgb_j, homography_flow(H, h, w), homography_flow(H_inv, h, w))
    if consistent_share(G_ij, G_ji, fb_px) > plain_share:
        return G_ij, G_ji, True
    inl = mask.reshape(-1).astype(bool)
    agree = [match_agreement(X, uv_i[inl], uv_j[inl], cfg.ransac_px) for X in (F_ij, G_ij)]
    if agree[0] < cfg.min_agreement <= agree[1]:  # plain DIS locked onto a wrong motion
        return G_ij, G_ji, True
    return F_ij, F_ji, False
