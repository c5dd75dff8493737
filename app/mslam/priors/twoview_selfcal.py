"""The camera of an uncalibrated video from many views: focal length and lens together.

Two-view estimates (:mod:`mslam.priors.twoview_focal`, :mod:`mslam.priors.twoview_lens`) see a
focal length only where a pair's epipolar geometry pins it, and a lens only where it bends the
flow clearly; a weak lens and the focal length trade against each other within what one pair
shows. Many views of the same points separate them, as structure from motion does: on the
7-Scenes clip COLMAP calibrates the colour camera at f = 500 px (640x480) with a radial
``k₁ = −0.043``, which the pairs cannot tell from the 60° guess (554 px) and no lens.

**The estimate** (before the first frame is tracked): point tracks through a few stretches of
the video at ``DETAIL_SIDE`` pixels (:mod:`mslam.priors.selfcal_tracks`); each stretch
(``STRETCHES`` of up to ``STRETCH_FRAMES`` frames, spread over the video; ``VIEWS`` views each)
reconstructed from the 60° guess with one focal length and one radial coefficient, shared by
its views, refined as it grows (:mod:`mslam.priors.selfcal_sfm`, :mod:`mslam.priors.selfcal_ba`).
Each stretch is a separate estimate.

It needs frames of at least ``DETAIL_SIDE`` pixels on the long side: from 160x120 tracks the
estimate on the clip re-rendered at 55° was 4.9 % short (benchmarks/RESULTS.md, "The camera
from many views"); smaller videos keep the two-view estimates.

**Used only where the stretches agree.** At least two stretches must reconstruct, each with
its focal length determined to ``MAX_SD_F`` (log units, from the adjustment's covariance)
and its lens to ``MAX_SD_K``, and every two of them must agree within ``AGREE_F`` and
``AGREE_K``: a camera that only turns or stands gives no starting pair, degenerate motion a
flat focal length, and a wrong reconstruction (a planar scene's twin solution) a stretch that
disagrees with the others. The camera in use is then the stretches' mean (log focal length
and coefficient); the frames are undistorted by the division model that best matches the
estimated lens (:func:`division_coefficient`). Otherwise the run falls back to the two-view
estimates.

Public names, in reading order:
    STRETCHES, STRETCH_FRAMES, VIEWS, MAX_SD_F, MAX_SD_K, AGREE_F, AGREE_K, CameraEstimate,
    stretches, division_coefficient, estimate_camera, decide_camera
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from mslam.datasets.frame import FrameSequence
from mslam.datasets.images import centre_scale
from mslam.priors.selfcal_sfm import Reconstruction, reconstruct
from mslam.priors.selfcal_tracks import DETAIL_SIDE, detail_frames, track
from mslam.priors.twoview_geometry import focal_guess_intrinsics

__all__ = [
    "AGREE_F",
    "AGREE_K",
    "MAX_SD_F",
    "MAX_SD_K",
    "STRETCHES",
    "STRETCH_FRAMES",
    "VIEWS",
    "CameraEstimate",
    "decide_camera",
    "division_coefficient",
    "estimate_camera",
    "stretches",
]

#: Stretches of the video reconstructed separately, their most frames, and views per stretch.
STRETCHES = 2
STRETCH_FRAMES = 150
VIEWS = 25
#: Fewest frames of a stretch.
MIN_FRAMES = 30
#: Largest standard deviation of a stretch's log focal length and radial coefficient.
MAX_SD_F = 0.03
MAX_SD_K = 0.02
#: Largest disagreement between two stretches: log focal length, radial coefficient. Measured
#: 2026-11-28 (benchmarks/RESULTS.md, "The camera from many views"): the two stretches of
#: renders with known cameras differ by 0.8-7.6 % (all within 3 % of the truth once averaged),
#: those of 150- and 300-frame stretches of the 7-Scenes kitchen by 0.3-11.8 % and up to 0.04.
AGREE_F = 0.08
AGREE_K = 0.04


@dataclass(frozen=True)
class CameraEstimate:
    """What the many-view estimate found (module docstring).

    Attributes:
        focal_scale: the focal length over the 60° guess (1 when not used).
        k: the radial coefficient (forward model, half-diagonal units) or 0.
        lam: the division coefficient the frames are undistorted by (0 when not used).
        used: whether the estimate replaces the guess. reason: one line on the decision.
        stretches: per stretch, ``[first frame, last frame + 1]`` and its estimate (or None).
    """

    focal_scale: float
    k: float
    lam: float
    used: bool
    reason: str
    stretches: tuple[dict[str, object], ...]

    def as_dict(self) -> dict[str, object]:
        return asdict(self)

    def record(self, guess_px: float) -> dict[str, object]:
        """The run's ``focal_estimate`` record (the keys of the two-view estimate's, with
        ``method``) for the 60° guess ``guess_px`` at the run's resolution."""
        lens = {"lam": self.lam, "k": self.k, "used": bool(self.lam), "lam_in_use": self.lam,
                "reason": f"radial k {self.k:+.3f} from many views: frames undistorted "
                          f"(division λ {self.lam:+.3f})"}  # fmt: skip
        return {"method": "many views", "guess_px": guess_px,
                "estimate_px": guess_px * self.focal_scale, "used": self.used,
                "scale": self.focal_scale, "reason": self.reason, "lens": lens,
                "many_views": self.as_dict()}  # fmt: skip


def stretches(n: int) -> list[tuple[int, int]]:
    """``[a, b)`` frame ranges of the stretches of an ``n``-frame video: ``STRETCHES`` equal
    parts, each at most ``STRETCH_FRAMES`` long, centred in its part; none shorter than
    ``MIN_FRAMES``."""
    part = n // STRETCHES
    L = min(part, STRETCH_FRAMES)
    if L < MIN_FRAMES:
        return []
    return [(k * part + (part - L) // 2, k * part + (part - L) // 2 + L) for k in range(STRETCHES)]


def division_coefficient(k: float) -> float:
    """The division coefficient ``λ`` (``x_u = x_d / (1 + λ|x_d|²)``) closest, over the image
    (radius 0–1 half diagonal, weighted by area), to the forward model ``x_d = x_u (1 + k|x_u|²)``
    of :mod:`mslam.priors.selfcal_ba`."""
    r_u = np.linspace(0.02, 1.0, 50)
    r_d = r_u * (1.0 + k * r_u**2)
    # x_u (1 + λ r_d²) = x_d  →  λ r_d² r_u = r_d − r_u: least squares with weights r (area)
    a, b, w = r_d**2 * r_u, r_d - r_u, r_u
    return float((w * a * b).sum() / (w * a * a).sum())


def _read(gray: Callable[[int], np.ndarray], a: int, b: int) -> list[np.ndarray] | None:
    """Detail frames ``a .. b - 1``, or None when one cannot be read or has another size."""
    try:
        grays = [gray(i) for i in range(a, b)]
    except (OSError, ValueError, cv2.error):
        return None
    return grays if all(g.shape == grays[0].shape for g in grays) else None


def _stretch(grays: list[np.ndarray] | None, seed: int) -> tuple[Reconstruction | None, float]:
    """One stretch's reconstruction and the guess's F (focal over half diagonal)."""
    if grays is None:
        return None, 0.0
    cv2.setRNGSeed(seed)  # RANSAC draws from the thread's generator: the same on every run
    H, W = grays[0].shape
    F0 = float(focal_guess_intrinsics(W, H)[0, 0]) / centre_scale(W, H)[1]
    views = np.unique(np.linspace(0, len(grays) - 1, VIEWS).round().astype(int))
    return reconstruct(track(grays), views, F0), F0


def estimate_camera(sequence: FrameSequence) -> CameraEstimate:
    """The many-view estimate of ``sequence``'s camera and its use (module docstring)."""
    ranges = stretches(len(sequence))
    if len(ranges) < 2:
        return CameraEstimate(1.0, 0.0, 0.0, False, "too few frames for two stretches", ())
    gray = detail_frames(sequence)
    try:
        side = max(gray(ranges[0][0]).shape)
    except (OSError, ValueError, cv2.error):
        side = 0
    if side < DETAIL_SIDE:
        why = f"frames of {side} px (< {DETAIL_SIDE} px): too little detail for many views"
        return CameraEstimate(1.0, 0.0, 0.0, False, why, ())
    # Read on this thread, in order (a video decodes forward); track and solve in parallel.
    jobs = [(_read(gray, a, b), a) for a, b in ranges]
    workers = max(1, min(len(ranges), os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        found = list(pool.map(lambda job: _stretch(*job), jobs))
    return decide_camera(ranges, found)


def _record(r: Reconstruction | None, F0: float, a: int, b: int) -> dict[str, object]:
    if r is None:
        return {"frames": [a, b], "reconstructed": False}
    sd = [float(x) if np.isfinite(x) else None for x in np.sqrt(np.diag(r.cov))]  # JSON-safe
    return {"frames": [a, b], "reconstructed": True, "focal_scale": r.F / F0, "k": r.k,
            "sd_log_focal": sd[0], "sd_k": sd[1], "views": r.views,
            "views_total": r.views_total, "points": r.points, "sigma_px": r.sigma_px}  # fmt: skip


def decide_camera(
    ranges: list[tuple[int, int]], found: list[tuple[Reconstruction | None, float]]
) -> CameraEstimate:
    """The estimate and its use from the stretches' reconstructions (module docstring)."""
    records = tuple(_record(r, F0, a, b) for (a, b), (r, F0) in zip(ranges, found, strict=True))

    def fallback(why: str) -> CameraEstimate:
        return CameraEstimate(
            1.0, 0.0, 0.0, False, f"{why}: the two-view estimates decide", records
        )

    good = [(r, F0) for r, F0 in found if r is not None]
    if len(good) < 2:
        return fallback(f"{len(good)} of {len(records)} stretches reconstructed")
    sd_f = max(float(np.sqrt(r.cov[0, 0])) for r, _ in good)
    sd_k = max(float(np.sqrt(r.cov[1, 1])) for r, _ in good)
    if sd_f > MAX_SD_F or sd_k > MAX_SD_K:
        return fallback(f"not determined (sd of log f {sd_f:.3f}, of k {sd_k:.3f})")
    logf = np.log([r.F / F0 for r, F0 in good])
    ks = np.array([r.k for r, _ in good])
    if np.ptp(logf) > AGREE_F or np.ptp(ks) > AGREE_K:
        return fallback(f"the stretches disagree (focal x{np.exp(np.ptp(logf)):.3f}, "
                        f"k by {np.ptp(ks):.3f})")  # fmt: skip
    scale, k = float(np.exp(logf.mean())), float(ks.mean())
    lam = division_coefficient(k)
    why = (f"{len(good)} stretches agree (focal x{np.exp(np.ptp(logf)):.3f}, k by {np.ptp(ks):.3f})"
           f": focal x{scale:.3f} the guess, lens k {k:+.3f}")  # fmt: skip
    return CameraEstimate(scale, k, lam, True, why, records)
