"""Photometric alignment of an image pair for optical flow — a gain between the images.

Auto-exposure changes a frame's brightness by a gain ``g`` (with a power-law tone curve
``(g·L)^γ = g^γ · L^γ``, still a gain on the encoded grey levels). DIS optical flow compares
raw grey levels: its patch search subtracts the patch means (an offset), but its variational
refinement assumes brightness constancy, so a gain between the two images moves the flow by
fractions of a pixel.

The gain is measured on the flow itself: over the pixels whose forward–backward error is below
``GAIN_FB_PX`` and whose grey levels are away from black and white in both images (clipping
breaks the gain model), ``g = exp(median(log(grey_j(u + F_ij(u)) / grey_i(u))))``. When
``|log g| > GAIN_TOL`` the two images are brought to a common exposure, the gain split evenly
(``grey_i · √g`` and ``grey_j / √g``, so that swapping the images swaps the results), the flow
is computed again, and the more self-consistent of the two flows is kept
(:func:`mslam.priors.twoview_dis.dense_flow`); otherwise the first flow stands, unchanged.

Measured on the 7-Scenes kitchen clip at 160x120 (2026-11-26). Pairs four frames apart with
the gain swinging between 1/2 and 2 over 60 frames (``benchmarks/hard_variants.py``,
``exposure``): 14.9 % of the pixels' flow lay more than 0.3 px from the unchanged pair's flow,
6.7 % with every pair aligned (the rest: clipped and coarser grey levels). The unchanged clip's
own pairs measure gains too (view-dependent brightness and the camera's auto-exposure, pairs
far apart): 42 % of the 313 flows of a run beyond 2 %, 5-10 % beyond 10 %. Realigning those
changes flows that were right, and the whole run is sensitive to them: with ``GAIN_TOL`` at a
10 % gain (0.1) the clip's runs gave trajectory errors of 3.54 cm forward, 6.84 cm mirrored,
4.33 cm portrait and 3.94 cm forward-and-back against 2.66 / 2.61 / 3.19 / 2.95 cm with no
alignment, and 3.18 cm against 5.78 cm on ``exposure``. From a 28 % gain (0.25, a third of a
stop, beyond the view-dependent brightness of ordinary pairs): 2.57 / 2.60 / 3.18 / 3.05 cm,
and 4.65 cm on ``exposure`` (31 keyframes against 34 without, 26 at 0.1). Single runs each;
``benchmarks/RESULTS.md``, "Exposure changes".

Public names, in reading order:
    GAIN_TOL, exposure_gain, common_exposure
"""

from __future__ import annotations

import cv2
import numpy as np

from mslam_ref.conventions import FloatArray

__all__ = ["GAIN_TOL", "common_exposure", "exposure_gain"]

#: Largest ``|log g|`` left alone (a 28 % gain, a third of a stop; module docstring).
GAIN_TOL = 0.25
#: Forward–backward error (pixels) below which a pixel's flow measures the gain.
GAIN_FB_PX = 0.5
#: Grey levels (exclusive) outside which a pixel may be clipped and does not measure the gain.
GAIN_LEVELS = (16.0, 240.0)
#: Fewest measuring pixels for a gain; with fewer the gain is 1.
GAIN_MIN_PIXELS = 100


def exposure_gain(
    grey_i: np.ndarray, grey_j: np.ndarray, F_ij: FloatArray, e_fb: FloatArray
) -> float:
    """Gain ``g`` of image j relative to image i, measured along the flow.

    Args:
        grey_i, grey_j: (H, W) uint8 grey images.
        F_ij: (H, W, 2) flow from i to j (pixels).
        e_fb: (H, W) its forward–backward error (pixels; ``inf`` where it leaves image j).

    Returns:
        ``exp(median(log(grey_j(u + F_ij(u)) / grey_i(u))))`` over the consistent, unclipped
        pixels; 1.0 when fewer than ``GAIN_MIN_PIXELS`` of them.
    """
    H, W = grey_i.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    map_u = u + F_ij[..., 0].astype(np.float32)
    map_v = v + F_ij[..., 1].astype(np.float32)
    b = cv2.remap(grey_j.astype(np.float32), map_u, map_v, cv2.INTER_LINEAR)
    a = grey_i.astype(np.float32)
    lo, hi = GAIN_LEVELS
    ok = (e_fb < GAIN_FB_PX) & (a > lo) & (a < hi) & (b > lo) & (b < hi)
    if int(ok.sum()) < GAIN_MIN_PIXELS:
        return 1.0
    return float(np.exp(np.median(np.log(b[ok] / a[ok]))))


def common_exposure(
    grey_i: np.ndarray, grey_j: np.ndarray, gain: float
) -> tuple[np.ndarray, np.ndarray]:
    """Two grey images brought to a common exposure, the gain split evenly between them.

    Args:
        grey_i, grey_j: (H, W) uint8 grey images (any sizes).
        gain: ``g`` of image j relative to image i (> 0), from :func:`exposure_gain`.

    Returns:
        (H, W) uint8 ``grey_i · √g`` and ``grey_j / √g`` (rounded, clipped to [0, 255]).
    """
    if not gain > 0:
        raise ValueError(f"gain: expected > 0, got {gain}")
    s = float(np.sqrt(gain))
    return _scaled(grey_i, s), _scaled(grey_j, 1.0 / s)


def _scaled(grey: np.ndarray, gain: float) -> np.ndarray:
    """(H, W) uint8 ``grey · gain``, rounded and clipped to [0, 255] (a lookup table)."""
    lut = np.clip(np.rint(np.arange(256) * gain), 0, 255).astype(np.uint8)
    return lut[grey]
