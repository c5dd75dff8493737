"""The radial distortion of an uncalibrated video, from the video, where the video shows it.

A pinhole model assumed for a lens that bends straight lines costs an uncalibrated run more
than a wrong focal length: views of the 7-Scenes kitchen re-rendered through a radial lens
(``benchmarks/novel_views.py --k1``) gave, RGB only, ATE 3.00 cm (60°, barrel) and 9.39 cm
(50°, barrel) against 0.88 and 1.50 cm for the same views without distortion; undistorted by
the estimate below first, 1.35 and 1.22 cm (benchmarks/RESULTS.md, "The lens from the
video"). Barrel distortion is also what makes the focal-length estimate
(:mod:`mslam.priors.twoview_focal`) run long: 37 % and 50 % on those two videos.

**The estimate** (inside the focal pre-pass, on the same pairs and flow samples): for each
division coefficient ``λ`` of ``LAMBDAS`` (``mslam.datasets.images``: pixels normalised by
the image's half diagonal, no focal length needed) the pair's flow end points are
undistorted and a fundamental matrix is fitted to them by least squares (normalised
8-point, on the pair's RANSAC inliers at ``λ = 0``); the pair's residual is the median
Sampson distance. Only the right ``λ`` makes the flow of a rigid scene exactly epipolar.
Each pair's curve is divided by its minimum and the curves are summed.

**Used only where clear.** The estimate replaces the pinhole model when at least
``MIN_PAIRS`` pairs entered, the minimum is not at an end of ``LAMBDAS``, the pinhole
(``λ = 0``) explains the flow at least ``MIN_GAIN`` times worse than the estimate (summed
curve), and a bootstrap over the pairs keeps ``λ = 0`` outside its 10–90 % range. On the
7-Scenes clip the pinhole is within 2 % of the best ``λ`` and within 15 % on every variant
of it (not used: undistorting the clip by ``λ = ±0.1`` made its ATE worse, 2.41 → 3.88 and
3.55 cm); on the distorted renders it is 1.32–1.87 times worse.

Public names, in reading order:
    LAMBDAS, MIN_GAIN, LensEstimate, bootstrap_range, residual_curve, decide_lens
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from mslam.datasets.images import division_undistort_points
from mslam.priors.twoview_geometry import sampson_distances
from mslam_ref.conventions import FloatArray

__all__ = [
    "LAMBDAS",
    "MIN_GAIN",
    "LensEstimate",
    "bootstrap_range",
    "decide_lens",
    "residual_curve",
]

#: Division coefficients searched, steps of 0.025 (image half diagonal = 1): at ``λ = -0.4`` a
#: corner of the undistorted image comes from 0.76 of the half diagonal (a strong barrel lens).
LAMBDAS = np.linspace(-0.4, 0.4, 33)
#: Least ratio of the pinhole's summed residual to the estimate's for the estimate to be used.
MIN_GAIN = 1.3
#: Fewest pairs, and bootstrap draws.
MIN_PAIRS = 12
BOOTSTRAP = 300


@dataclass(frozen=True)
class LensEstimate:
    """What the pre-pass found of the lens (module docstring).

    Attributes:
        lam: the summed curve's minimum (division coefficient), or None with too few pairs.
        gain: the pinhole's summed residual over the minimum's (1 = no evidence of distortion).
        low, high: the bootstrap's 10 % and 90 % ``λ`` (None without an estimate).
        pairs: pairs that entered.
        used: whether the frames are undistorted by ``lam``.
        reason: one line on the decision.
    """

    lam: float | None
    gain: float
    low: float | None
    high: float | None
    pairs: int
    used: bool
    reason: str

    @property
    def lam_in_use(self) -> float:
        """The division coefficient applied to the frames (0 when the pinhole stays)."""
        return float(self.lam) if self.used and self.lam is not None else 0.0

    def as_dict(self) -> dict[str, object]:
        return {**asdict(self), "lam_in_use": self.lam_in_use}


def bootstrap_range(
    curves: FloatArray, grid: FloatArray, seed: int = 0, draws: int = BOOTSTRAP
) -> tuple[float, float]:
    """10 % and 90 % of the minimum of ``curves`` (P, len(grid)) summed over pairs resampled
    with replacement ``draws`` times, in units of ``grid``."""
    P = len(curves)
    rng = np.random.default_rng(seed)
    boot = [int(np.argmin(curves[rng.integers(0, P, P)].sum(0))) for _ in range(draws)]
    lo, hi = np.percentile(grid[boot], [10, 90])
    return float(lo), float(hi)


def residual_curve(uv_i: FloatArray, uv_j: FloatArray, W: int, H: int) -> FloatArray | None:
    """Median Sampson distance (px²) of the least-squares F for each ``λ`` of ``LAMBDAS``,
    shape ``(len(LAMBDAS),)``; ``uv_i``, ``uv_j``: (N, 2) flow end points in a (W, H) image,
    already RANSAC inliers. None where a fit fails."""
    out = np.empty(len(LAMBDAS))
    for n, lam in enumerate(LAMBDAS):
        a = division_undistort_points(uv_i, float(lam), W, H)
        b = division_undistort_points(uv_j, float(lam), W, H)
        try:
            F, _ = cv2.findFundamentalMat(a, b, cv2.FM_8POINT)
        except cv2.error:
            return None
        if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
            return None
        out[n] = np.median(sampson_distances(np.asarray(F, np.float64), a, b) ** 2)
    return out if np.all(np.isfinite(out)) and out.min() > 0 else None


def decide_lens(curves: FloatArray, seed: int = 0) -> LensEstimate:
    """The estimate and its use (module docstring) from the pairs' residual curves
    ``(P, len(LAMBDAS))``."""
    P = len(curves)
    if P < MIN_PAIRS:
        return LensEstimate(None, 1.0, None, None, P, False, f"{P} pairs: pinhole assumed")
    rel = curves / curves.min(1, keepdims=True)
    total = rel.sum(0)
    best = int(np.argmin(total))
    zero = int(np.argmin(np.abs(LAMBDAS)))
    gain = float(total[zero] / total[best])
    lo, hi = bootstrap_range(rel, LAMBDAS, seed)
    lam = float(LAMBDAS[best])

    def verdict(used: bool, why: str) -> LensEstimate:
        return LensEstimate(lam, gain, lo, hi, P, used, why)

    if best in (0, len(LAMBDAS) - 1):
        return verdict(False, f"λ {lam:+.3f} at the end of the searched span: pinhole assumed")
    if gain < MIN_GAIN or lo <= 0.0 <= hi:
        return verdict(False, f"no clear distortion (pinhole residual x{gain:.2f}, λ 10-90 % "
                              f"{lo:+.3f} to {hi:+.3f}): pinhole assumed")  # fmt: skip
    kind = "barrel" if lam < 0 else "pincushion"
    return verdict(True, f"{kind} distortion λ {lam:+.3f} (pinhole residual x{gain:.2f}): "
                         "frames undistorted")  # fmt: skip
