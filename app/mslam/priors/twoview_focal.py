"""The focal length of an uncalibrated video, from the video, where the video determines it.

Uncalibrated, the two-view prior assumes a 60° field of view across the long side
(:func:`~mslam.priors.twoview_geometry.focal_guess_intrinsics`). A camera with another lens
makes every pair's rotation and structure wrong in a way no later step undoes: re-rendered
views of the 7-Scenes kitchen with a 50° lens and a hand-held wobble (``benchmarks/novel_views.py``)
gave an ATE of 4.95 cm with the guess and 0.79 cm calibrated (benchmarks/RESULTS.md).

**The estimate** (a pre-pass over the sequence, before the first frame is tracked): for
pairs ``GAPS`` frames apart, spread over the whole sequence, the fundamental matrix ``F`` of
the pair's consistent flow (RANSAC), and for each focal length ``f`` of ``SEARCH`` times the
guess the classical self-calibration cost of the essential matrix ``E_f = K_fᵀ F K_f``: its two
non-zero singular values are equal for the right ``f`` (``(σ₁ − σ₂) / (σ₁ + σ₂)``, principal
point at the image centre). Pairs whose flow is a rotation for some focal length (no
epipolar geometry) are left out. The estimate minimises the sum of the pairs' costs.

**Used only where determined, and against the guess.** Forward motion, or a camera turning
about an axis in the plane of its motion, leaves ``f`` undetermined (the cost is flat). A
bootstrap over the pairs gives the estimate's 10–90 % range; the estimate replaces the guess
when at least ``MIN_PAIRS`` pairs entered, the range spans less than ``MAX_SPREAD`` (ratio of
its ends), the estimate is not at an end of ``SEARCH``, and the range lies outside
``[guess, LONG_BIAS · guess]``: on flow the minimum runs long (0–8 % on rendered videos,
10–25 % on the 7-Scenes clip, whose colour camera the guess fits within about 5 %), so an estimate
a little longer than the guess says nothing against it. The run's ``summary.json`` says
which (``focal_estimate``).

Public names, in reading order:
    GAPS, SEARCH, MIN_PAIRS, MAX_SPREAD, LONG_BIAS, FocalEstimate, kruppa_cost, pair_cost,
    estimate_focal, pair_costs, decide
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from mslam.datasets.frame import FrameSequence
from mslam.priors.twoview_flow import guided_flow, sift_keypoints
from mslam.priors.twoview_geometry import focal_guess_intrinsics, forward_backward_error
from mslam.priors.twoview_homography import homography_fit
from mslam_ref.conventions import FloatArray

__all__ = [
    "GAPS",
    "LONG_BIAS",
    "MAX_SPREAD",
    "MIN_PAIRS",
    "SEARCH",
    "FocalEstimate",
    "estimate_focal",
    "decide",
    "kruppa_cost",
    "pair_cost",
    "pair_costs",
]

#: Frame gaps of the pairs, and the most pairs per gap (evenly spread over the sequence).
GAPS = (4, 8)
PAIRS_PER_GAP = 16
#: Focal lengths searched, as factors of the guess: fields of view 32–98° across the long side.
SEARCH = np.geomspace(0.5, 2.0, 97)
#: Fewest pairs with epipolar geometry for an estimate.
MIN_PAIRS = 12
#: Largest ratio of the bootstrap's 90 % and 10 % estimates for a determined focal length.
MAX_SPREAD = 1.15
#: The estimate runs long: 0-8 % on rendered videos of known focal length, 10-25 % on the
#: 7-Scenes clip's variants (2026-11-27, benchmarks/RESULTS.md). A range that reaches into [guess, LONG_BIAS · guess] is no
#: evidence against the guess.
LONG_BIAS = 1.15
#: Flow vectors used per pair: forward–backward error below FB_PX pixels, at most SAMPLES.
FB_PX = 0.3
SAMPLES = 2000
#: Pairs with fewer consistent vectors, or whose flow is a rotation (homography parallax
#: below ROTATION_PX pixels for some focal length), are left out.
MIN_VECTORS = 300
ROTATION_PX = 2.0
BOOTSTRAP = 300


@dataclass(frozen=True)
class FocalEstimate:
    """What the pre-pass found (module docstring); focal lengths in pixels at the frames'
    resolution.

    Attributes:
        guess_px: the 60° guess.
        estimate_px: the sum-of-costs minimum, or None with too few pairs.
        low_px, high_px: the bootstrap's 10 % and 90 % estimates (None without an estimate).
        pairs: pairs with epipolar geometry that entered the sum.
        used: whether ``estimate_px`` replaces the guess.
        reason: one line on the decision.
    """

    guess_px: float
    estimate_px: float | None
    low_px: float | None
    high_px: float | None
    pairs: int
    used: bool
    reason: str

    @property
    def scale(self) -> float:
        """The focal length in use over the guess (1 when the guess stays)."""
        return self.estimate_px / self.guess_px if self.used and self.estimate_px else 1.0

    def as_dict(self) -> dict[str, object]:
        return {**asdict(self), "scale": self.scale}


def kruppa_cost(F: FloatArray, K: FloatArray, factors: FloatArray = SEARCH) -> FloatArray:
    """``(σ₁ − σ₂) / (σ₁ + σ₂)`` of ``K_fᵀ F K_f`` for each focal length ``factors · f_K``
    (``K_f``: K with that focal length); shape ``(len(factors),)``."""
    out = np.empty(len(factors))
    for n, s in enumerate(factors):
        K_f = np.asarray(K, np.float64).copy()
        K_f[0, 0] *= s
        K_f[1, 1] *= s
        sv = np.linalg.svd(K_f.T @ F @ K_f, compute_uv=False)
        out[n] = (sv[0] - sv[1]) / max(sv[0] + sv[1], 1e-300)
    return out


def pair_cost(
    rgb_i: np.ndarray, rgb_j: np.ndarray, K: FloatArray, seed: int = 0
) -> FloatArray | None:
    """:func:`kruppa_cost` of a pair's fundamental matrix, or None for a pair left out (too
    few consistent flow vectors, a rotation, no F). Images (H, W, 3) uint8."""
    kp_i, kp_j = (lambda: sift_keypoints(rgb_i)), (lambda: sift_keypoints(rgb_j))
    F_ij, F_ji, _ = guided_flow(rgb_i, rgb_j, kp_i, kp_j)  # the prior's flow, SIFT-seeded
    e_fb, _ = forward_backward_error(F_ij, F_ji)
    v, u = np.nonzero(e_fb < FB_PX)
    if len(u) < MIN_VECTORS:
        return None
    sel = np.random.default_rng(seed).choice(len(u), min(SAMPLES, len(u)), replace=False)
    uv_i = np.stack([u[sel], v[sel]], -1).astype(np.float64)
    uv_j = uv_i + F_ij[v[sel], u[sel]]
    if homography_fit(uv_i, uv_j, K, focal_free=True).parallax_px < ROTATION_PX:
        return None
    try:
        F, _ = cv2.findFundamentalMat(uv_i, uv_j, cv2.FM_RANSAC, 0.5, 0.999)
    except cv2.error:
        return None
    if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        return None
    return kruppa_cost(np.asarray(F, np.float64), K)


def estimate_focal(frames: FrameSequence, seed: int = 0) -> FocalEstimate:
    """The focal length of ``frames`` (a sequence of ``Frame``, all of one size; unreadable
    frames are skipped), module docstring."""
    costs, guess = pair_costs(frames, seed)
    return decide(costs, guess, seed)


def pair_costs(frames: FrameSequence, seed: int = 0) -> tuple[FloatArray, float]:
    """``(costs (P, len(SEARCH)), guess_px)``: :func:`pair_cost` of the pairs that have
    epipolar geometry among those of the module docstring, and the 60° guess."""
    n = len(frames)
    pairs = [(int(i), int(i) + gap) for gap in GAPS if n > gap
             for i in np.unique(np.linspace(0, n - 1 - gap, PAIRS_PER_GAP).round())]  # fmt: skip
    size, jobs = None, []
    for i, j in pairs:
        try:
            a, b = frames[i], frames[j]
        except (OSError, ValueError, cv2.error):
            continue
        size = size or a.shape  # (H, W) of the first readable pair
        if a.shape == b.shape == size:
            jobs.append((a.rgb, b.rgb, seed + i))
    H, W = size or frames[0].shape
    K = focal_guess_intrinsics(W, H)
    # Pairs are independent and OpenCV releases the GIL: one thread per core (same results).
    with ThreadPoolExecutor(max_workers=max(1, min(len(jobs), os.cpu_count() or 1))) as pool:
        found = list(pool.map(lambda job: pair_cost(job[0], job[1], K, job[2]), jobs))
    costs = [c for c in found if c is not None]
    return np.asarray(costs).reshape(-1, len(SEARCH)), float(K[0, 0])


def decide(costs: FloatArray, guess: float, seed: int = 0) -> FocalEstimate:
    """The estimate and its use (module docstring) from the pairs' cost curves
    ``(P, len(SEARCH))`` and the guess (pixels)."""
    P = len(costs)
    if P < MIN_PAIRS:
        why = f"{P} pairs with epipolar geometry (< {MIN_PAIRS}): the 60° guess is used"
        return FocalEstimate(guess, None, None, None, P, False, why)
    best = int(np.argmin(costs.sum(0)))
    rng = np.random.default_rng(seed)
    boot = [int(np.argmin(costs[rng.integers(0, P, P)].sum(0))) for _ in range(BOOTSTRAP)]
    lo, hi = np.percentile(SEARCH[boot], [10, 90]) * guess
    est = float(SEARCH[best] * guess)
    if best in (0, len(SEARCH) - 1):
        why = "at the end of the searched span: the 60° guess is used"
        return FocalEstimate(guess, est, float(lo), float(hi), P, False, why)
    if hi / lo > MAX_SPREAD:
        why = (
            f"not determined (10-90 % range x{hi / lo:.2f} > x{MAX_SPREAD}): the 60° guess is used"
        )
        return FocalEstimate(guess, est, float(lo), float(hi), P, False, why)
    if lo <= guess * LONG_BIAS and hi >= guess:
        why = (f"{est:.1f} px, within the estimator's long bias of the guess (10-90 % range "
               f"{lo:.1f}-{hi:.1f} px): the 60° guess is used")  # fmt: skip
        return FocalEstimate(guess, est, float(lo), float(hi), P, False, why)
    why = f"determined (10-90 % range x{hi / lo:.2f}): used instead of the 60° guess"
    return FocalEstimate(guess, est, float(lo), float(hi), P, True, why)
