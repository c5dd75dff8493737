"""Planar scenes in the two-view prior — the ambiguity of the relative pose, and a third view.

The two-view prior (:mod:`mslam.priors.twoview`) replaces MASt3R's pairwise pointmaps (paper
§3) by classical geometry: relative pose from the essential matrix, then triangulation. When
the correspondences all lie on one plane (a wall filling the view), the epipolar geometry does
not determine the pose: the flow is a homography ``H ~ R + t nᵀ/d``, and H has two physically
valid decompositions ``(R, t, n)`` and ``(R', t', n')`` that explain every correspondence
equally well (Longuet-Higgins 1986; Hartley & Zisserman §13.4 and §18.5.3). For small motions
the wrong one roughly swaps the roles of ``t`` and ``n``: a sideways move along a wall becomes
a move towards an oblique wall. Sampson distances cannot choose (measured on the synthetic loop
at 160x120: in 6 of 8 wall-facing pairs with a 4-9 frame gap the wrong decomposition had the
*lower* robust Sampson cost; its rotation was 1-8° and its translation direction 25-68° off),
and the triangulated pointmap is then a plane with the wrong tilt — with full confidence.

A third view resolves it (the classical remedy): the structure already reconstructed for
image i or j by an earlier, non-degenerate pair (the prior keeps each image's last
reconstruction for ``mono``). :func:`pose_candidates` lists the RANSAC
essential-matrix pose and both homography decompositions, each refined on Sampson distances;
:func:`choose_pose` keeps the candidates whose cost is within ``ambiguity`` of the best (the
ones the pair itself cannot tell apart) and picks among them the one whose triangulated
depths of image i and j agree best (up to scale) with their remembered depths. Without a remembered
view, the lowest cost wins. :class:`ReferenceDepths` remembers, per image, the depth of its
reconstruction with the widest median triangulation angle so far: the best-determined one, so
that a later narrow pair that chose a wrong hypothesis does not become the reference (on the
synthetic loop, 240 frames, focal length from the video: ATE 8.7 cm with the latest pair's
depth, 5.5 cm with the widest; 2026-11-27).

Public names, in reading order:
    pose_candidates, depth_disagreement, choose_pose, ReferenceDepths
"""

from __future__ import annotations

import cv2
import numpy as np

from mslam.priors.cache import ByteLRU
from mslam.priors.twoview_geometry import (
    front_counts,
    refine_pose,
    sampson_residuals,
    triangulate_midpoint,
)
from mslam_ref.conventions import FloatArray

__all__ = ["ReferenceDepths", "choose_pose", "depth_disagreement", "pose_candidates"]


#: Correspondences each hypothesis is refined on (a regular subsample of the inliers).
REFINE_POINTS = 600


def _huber_cost(r: FloatArray, delta: float) -> float:
    a = np.abs(r)
    return float(np.mean(np.where(a < delta, 0.5 * a**2, delta * (a - 0.5 * delta))))


def _front_sign(uv_i, uv_j, K, R, t) -> FloatArray:
    """``t`` or ``-t``, whichever puts more triangulated points in front of both cameras."""
    n_pos, n_neg = front_counts(uv_i, uv_j, K, R, t)
    return t if n_pos >= n_neg else -t


def _add_unsigned(hyps: list[tuple[FloatArray, FloatArray]], R: FloatArray, t: FloatArray) -> None:
    """Append ``(R, t)`` unless ``(R, -t)`` is already listed.

    OpenCV returns each homography decomposition twice, as ``(R, t, n)`` and ``(R, -t, -n)``.
    Sampson distances do not change when ``t`` changes sign, so both refine to the same pose
    up to the sign of ``t``, which :func:`_front_sign` then sets alike: the second is a
    duplicate that the merge in :func:`pose_candidates` would drop after refining it.
    """
    for R2, t2 in hyps:
        if np.array_equal(R, R2) and np.allclose(t, -t2, rtol=0.0, atol=1e-12):
            return
    hyps.append((R, t))


def pose_candidates(
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    R_ji: FloatArray,
    t_ji: FloatArray,
    ransac_px: float = 1.0,
    huber_px: float = 0.3,
) -> list[tuple[FloatArray, FloatArray, float]]:
    """Refined pose hypotheses of a pair: ``[(R_ji, t_ji, cost), ...]``, lowest cost first.

    The essential-matrix pose ``(R_ji, t_ji)`` and every decomposition of the RANSAC
    homography of the correspondences (``cv2.decomposeHomographyMat``, one of each sign pair,
    :func:`_add_unsigned`) are refined by
    :func:`~mslam.priors.twoview_geometry.refine_pose`; the sign of ``t`` is set by
    cheirality; near-duplicates (< 0.5° apart in rotation and translation direction) are
    merged. ``cost`` is the mean Huber (``huber_px``) Sampson distance.

    Args:
        uv_i, uv_j: (N, 2) inlier correspondences. K: (3, 3). R_ji (3, 3), t_ji (3,).

    Returns:
        at least the refined essential-matrix pose.
    """
    hyps = [(R_ji, t_ji)]
    if len(uv_i) >= 8:
        try:
            Hm, _ = cv2.findHomography(uv_i, uv_j, cv2.RANSAC, ransac_px)
        except cv2.error:
            Hm = None
        if Hm is not None and np.all(np.isfinite(Hm)):
            _, Rs, ts, _ = cv2.decomposeHomographyMat(Hm, K)
            for R, t in zip(Rs, ts):
                t = np.asarray(t, np.float64).ravel()
                if np.linalg.norm(t) > 1e-9:  # zero translation: a rotation, no candidate
                    _add_unsigned(hyps, np.asarray(R, np.float64), t / np.linalg.norm(t))
    out: list[tuple[FloatArray, FloatArray, float]] = []
    # Hypotheses are refined on a regular subsample (REFINE_POINTS); the caller polishes the
    # chosen one on all correspondences.
    sub = np.linspace(0, len(uv_i) - 1, min(len(uv_i), REFINE_POINTS)).astype(np.int64)
    for R0, t0 in hyps:
        R, t = refine_pose(uv_i[sub], uv_j[sub], K, R0, t0, huber_px)
        t = _front_sign(uv_i, uv_j, K, R, t)
        cost = _huber_cost(sampson_residuals(uv_i, uv_j, K, R, t), huber_px)
        dup = False
        for R2, t2, _ in out:
            cos_r = np.clip((np.trace(R.T @ R2) - 1) / 2, -1, 1)
            if (
                np.degrees(np.arccos(cos_r)) < 0.5
                and np.degrees(np.arccos(np.clip(t @ t2, -1, 1))) < 0.5
            ):
                dup = True
                break
        if not dup:
            out.append((R, t, cost))
    return sorted(out, key=lambda h: h[2])


def depth_disagreement(
    uv_i: FloatArray, uv_j: FloatArray, K: FloatArray, R: FloatArray, t: FloatArray,
    z_ref: FloatArray, in_j: bool = False,
) -> float:  # fmt: skip
    """Scale-free disagreement of a hypothesis' depths with reference depths of one image.

    ``z`` are the depths, in camera i (or j with ``in_j``), of the midpoint triangulation of
    the correspondences; ``z_ref`` (H, W) the reference depth of that image (any scale),
    looked up at ``uv_i`` (or ``uv_j``). Returns the median absolute deviation of
    ``log z - log z_ref`` about its median (``inf`` when fewer than 20 points triangulate).
    """
    X, _, ok = triangulate_midpoint(uv_i, uv_j, K, R, t)
    uv = uv_i
    if in_j:
        X, uv = X @ R.T + t, uv_j
    H, W = z_ref.shape
    u = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, W - 1)
    v = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, H - 1)
    zr = z_ref[v, u]
    ok &= (X[:, 2] > 0) & (zr > 0)
    if ok.sum() < 20:
        return float("inf")
    d = np.log(np.where(ok, X[:, 2], 1.0)[ok]) - np.log(zr[ok])
    return float(np.median(np.abs(d - np.median(d))))


def choose_pose(
    cands: list[tuple[FloatArray, FloatArray, float]],
    uv_i: FloatArray,
    uv_j: FloatArray,
    K: FloatArray,
    z_ref_i: FloatArray | None,
    z_ref_j: FloatArray | None = None,
    ambiguity: float = 1.5,
) -> tuple[FloatArray, FloatArray, bool]:
    """Pick a hypothesis (module docstring): ``(R_ji, t_ji, ambiguous)``.

    Args:
        cands: :func:`pose_candidates` (lowest cost first).
        uv_i, uv_j: (N, 2) correspondences. K: (3, 3).
        z_ref_i, z_ref_j: (H, W) remembered depths of image i and of image j (any scales),
            or None; the disagreements with both are added.
        ambiguity: hypotheses whose cost is below ``ambiguity`` times the best one's are
            indistinguishable by the pair.

    Returns:
        the chosen pose and whether more than one hypothesis was indistinguishable.
    """
    best = cands[0][2]
    tied = [c for c in cands if c[2] <= ambiguity * best + 1e-12]
    refs = [(z, side) for z, side in ((z_ref_i, False), (z_ref_j, True)) if z is not None]
    if len(tied) == 1 or not refs:
        return cands[0][0], cands[0][1], len(tied) > 1
    scores = [sum(depth_disagreement(uv_i, uv_j, K, R, t, z, side) for z, side in refs)
              for R, t, _ in tied]  # fmt: skip
    k = int(np.argmin(scores))
    return tied[k][0], tied[k][1], True


class ReferenceDepths:
    """Per image, the depth of its widest-angle two-view reconstruction (module docstring).

    Args:
        max_bytes: bound of the store (a ``ByteLRU``: the images least recently stored or
            looked up go first, so a keyframe's reference stays while frames are paired with it).
    """

    def __init__(self, max_bytes: int) -> None:
        self._store = ByteLRU(max_bytes)

    def offer(self, index: int, z: FloatArray, angle_deg: float) -> None:
        """Keep depth ``z`` (H, W) of image ``index``, triangulated at a median angle of
        ``angle_deg``, unless an earlier one of the same size was wider."""
        old = self._store.peek(index)
        if old is None or old[0].shape != z.shape or angle_deg >= old[1]:
            self._store.put(index, (np.array(z, np.float64), float(angle_deg)))

    def depth(self, index: int, shape: tuple[int, int]) -> FloatArray | None:
        """The kept depth of image ``index`` when it is ``shape`` (H, W), else None."""
        if index not in self._store:
            return None
        ref = self._store.get(index, lambda: None)  # a hit, now the most recent entry
        return None if ref is None or ref[0].shape != tuple(shape) else ref[0]
