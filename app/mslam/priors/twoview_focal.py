"""The focal length of an uncalibrated video, from the video, where the video determines it.

Uncalibrated, the two-view prior assumes a 60° field of view across the long side
(:func:`~mslam.priors.twoview_geometry.focal_guess_intrinsics`). A camera with another lens
makes every pair's rotation and structure wrong in a way no later step undoes: re-rendered
views of the 7-Scenes kitchen with a 50° lens and a hand-held wobble
(``benchmarks/novel_views.py``) gave an ATE of 4.95 cm with the guess and 0.79 cm calibrated (benchmarks/RESULTS.md).

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

**The lens first.** On the same pairs and flow samples the pre-pass first looks for radial
distortion (:mod:`mslam.priors.twoview_lens`); where it finds it clearly, the pairs' end points
are undistorted before their ``F`` is fitted, and the run undistorts its frames
(``mslam.datasets.views.DivisionUndistortedSequence``). Barrel distortion otherwise passes for
a longer focal length.

Public names, in reading order:
    GAPS, SEARCH, MIN_PAIRS, MAX_SPREAD, LONG_BIAS, FocalEstimate, kruppa_cost, pair_samples,
    pair_cost, lens_curve, estimate_focal, pair_costs, pair_indices, lens_and_pair_costs,
    decide
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from mslam.datasets.frame import FrameSequence
from mslam.datasets.images import division_undistort_points
from mslam.priors.twoview_flow import guided_flow, sift_keypoints
from mslam.priors.twoview_geometry import focal_guess_intrinsics, forward_backward_error
from mslam.priors.twoview_homography import homography_fit
from mslam.priors.twoview_lens import (
    LAMBDAS,
    LensEstimate,
    bootstrap_range,
    decide_lens,
    residual_curve,
)
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
    "lens_and_pair_costs",
    "lens_curve",
    "pair_cost",
    "pair_costs",
    "pair_indices",
    "pair_samples",
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
#: 7-Scenes clip's variants (2026-11-27, benchmarks/RESULTS.md). A range that reaches into
#: [guess, LONG_BIAS · guess] is no evidence against the guess.
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
        lens: the lens found on the same pairs (:mod:`mslam.priors.twoview_lens`), or None.
    """

    guess_px: float
    estimate_px: float | None
    low_px: float | None
    high_px: float | None
    pairs: int
    used: bool
    reason: str
    lens: LensEstimate | None = None

    @property
    def scale(self) -> float:
        """The focal length in use over the guess (1 when the guess stays)."""
        return self.estimate_px / self.guess_px if self.used and self.estimate_px else 1.0

    def as_dict(self) -> dict[str, object]:
        out = {k: v for k, v in asdict(self).items() if k != "lens"}
        return {**out, "scale": self.scale, "lens": self.lens and self.lens.as_dict()}


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


def pair_samples(
    rgb_i: np.ndarray, rgb_j: np.ndarray, K: FloatArray, seed: int = 0
) -> tuple[FloatArray, FloatArray] | None:
    """A pair's consistent flow end points ``(uv_i, uv_j)``, each (N, 2), N ≤ ``SAMPLES``, or
    None for a pair left out (too few consistent vectors, a rotation). Images (H, W, 3) uint8."""
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
    return uv_i, uv_j


def _fundamental(uv_i: FloatArray, uv_j: FloatArray, px: float) -> tuple[FloatArray, np.ndarray]:
    """RANSAC F (threshold ``px``) and its inlier mask (N,), or raises ValueError."""
    try:
        F, mask = cv2.findFundamentalMat(uv_i, uv_j, cv2.FM_RANSAC, px, 0.999)
    except cv2.error as exc:
        raise ValueError(str(exc)) from None
    if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        raise ValueError("no fundamental matrix")
    return np.asarray(F, np.float64), mask.reshape(-1).astype(bool)


def pair_cost(uv_i: FloatArray, uv_j: FloatArray, K: FloatArray) -> FloatArray | None:
    """:func:`kruppa_cost` of the RANSAC fundamental matrix of a pair's flow end points
    (:func:`pair_samples`, undistorted where the lens was estimated), or None without one."""
    try:
        return kruppa_cost(_fundamental(uv_i, uv_j, 0.5)[0], K)
    except ValueError:
        return None


def lens_curve(uv_i: FloatArray, uv_j: FloatArray, W: int, H: int) -> FloatArray | None:
    """:func:`mslam.priors.twoview_lens.residual_curve` of a pair, on its inliers of a loose
    RANSAC (2 px: outliers out, distortion in), or None."""
    try:
        inl = _fundamental(uv_i, uv_j, 2.0)[1]
    except ValueError:
        return None
    return residual_curve(uv_i[inl], uv_j[inl], W, H) if inl.sum() >= MIN_VECTORS // 2 else None


def estimate_focal(frames: FrameSequence, seed: int = 0) -> FocalEstimate:
    """The focal length (and lens) of ``frames`` (a sequence of ``Frame``, all of one size;
    unreadable frames are skipped), module docstring."""
    costs, guess, lens = lens_and_pair_costs(frames, seed)
    return dataclasses.replace(decide(costs, guess, seed), lens=lens)


def pair_costs(frames: FrameSequence, seed: int = 0) -> tuple[FloatArray, float]:
    """``(costs (P, len(SEARCH)), guess_px)`` of :func:`lens_and_pair_costs`."""
    return lens_and_pair_costs(frames, seed)[:2]


def pair_indices(n: int) -> list[tuple[int, int]]:
    """``(i, j)`` frame indices of the pre-pass's pairs in a sequence of ``n`` frames: for each
    gap of ``GAPS`` (shorter than the sequence), up to ``PAIRS_PER_GAP`` pairs spread evenly."""
    return [(int(i), int(i) + gap) for gap in GAPS if n > gap
            for i in np.unique(np.linspace(0, n - 1 - gap, PAIRS_PER_GAP).round())]  # fmt: skip


def lens_and_pair_costs(
    frames: FrameSequence, seed: int = 0
) -> tuple[FloatArray, float, LensEstimate]:
    """``(costs (P, len(SEARCH)), guess_px, lens)``: the lens of the pairs of the module
    docstring, then :func:`pair_cost` of those that have epipolar geometry (their end points
    undistorted by the lens where it is used), and the 60° guess."""
    size, jobs = None, []
    for i, j in pair_indices(len(frames)):
        try:
            a, b = frames[i], frames[j]
        except (OSError, ValueError, cv2.error):
            continue
        size = size or a.shape  # (H, W) of the first readable pair
        if a.shape == b.shape == size:
            jobs.append((a.rgb, b.rgb, seed + i))
    H, W = size or frames[0].shape
    K = focal_guess_intrinsics(W, H)

    def job(rgb_i, rgb_j, sd):
        found = pair_samples(rgb_i, rgb_j, K, sd)
        return None if found is None else (*found, lens_curve(*found, W, H))

    # Pairs are independent and OpenCV releases the GIL: one thread per core (same results).
    with ThreadPoolExecutor(max_workers=max(1, min(len(jobs), os.cpu_count() or 1))) as pool:
        found = [f for f in pool.map(lambda jb: job(*jb), jobs) if f is not None]
        curves = [c for *_, c in found if c is not None]
        lens = decide_lens(np.asarray(curves).reshape(-1, len(LAMBDAS)), seed)
        lam = lens.lam_in_use
        und = (lambda uv: division_undistort_points(uv, lam, W, H)) if lam else (lambda uv: uv)
        costs = [c for c in pool.map(lambda f: pair_cost(und(f[0]), und(f[1]), K), found)
                 if c is not None]  # fmt: skip
    return np.asarray(costs).reshape(-1, len(SEARCH)), float(K[0, 0]), lens


def decide(costs: FloatArray, guess: float, seed: int = 0) -> FocalEstimate:
    """The estimate and its use (module docstring) from the pairs' cost curves
    ``(P, len(SEARCH))`` and the guess (pixels)."""
    P = len(costs)
    if P < MIN_PAIRS:
        why = f"{P} pairs with epipolar geometry (< {MIN_PAIRS}): the 60° guess is used"
        return FocalEstimate(guess, None, None, None, P, False, why)
    best = int(np.argmin(costs.sum(0)))
    lo, hi = (x * guess for x in bootstrap_range(costs, SEARCH, seed, BOOTSTRAP))
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
