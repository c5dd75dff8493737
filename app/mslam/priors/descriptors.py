"""Stand-in for MASt3R's local-feature head — dense patch descriptors from the image alone.

MASt3R predicts a 24-D unit descriptor per pixel (paper §3.2 uses it to refine matches in a
small window). Without the network, a fixed random projection of a normalised colour patch
plays that role: it is deterministic, identical for every image (so descriptors of two images
are comparable), varies smoothly with the pixel position (the image is blurred first and the
patch taps are spaced by ``step``), and discriminates between textured locations.

``D(u, v) = normalize(P^T z(u, v))`` with ``z`` the 3·p² samples of the blurred image on a p x p
grid of spacing ``step`` around (u, v), minus their mean and divided by their standard deviation
(plus ``eps``), and ``P`` a fixed (3p², F) Gaussian matrix. ``contrast(u, v)`` is that standard
deviation; the priors turn it into the descriptor confidence Q.

Public names, in reading order:
    DescriptorConfig, patch_descriptors
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from mslam_ref.conventions import FloatArray

__all__ = ["DescriptorConfig", "patch_descriptors"]

#: Image rows per block of the patch matrix (bounds its memory at H-independent size).
_ROWS = 16


@dataclass(frozen=True)
class DescriptorConfig:
    """Patch descriptor parameters.

    Attributes:
        dim: descriptor dimension F (MASt3R: 24).
        patch: p, taps per side (odd).
        step: spacing of the taps in pixels.
        blur_sigma: Gaussian blur of the image before sampling (pixels).
        eps: added to the patch standard deviation (flat patches stay finite).
        seed: seed of the projection matrix (the same for every image).
        cache_bytes: bound of the priors' per-frame cache (``mslam.priors.cache``).
    """

    dim: int = 24
    patch: int = 7
    step: int = 1
    blur_sigma: float = 0.5
    eps: float = 0.02
    seed: int = 24
    cache_bytes: int = 128 * 2**20


def _projection(cfg: DescriptorConfig) -> FloatArray:
    rng = np.random.default_rng([cfg.seed, cfg.patch, cfg.dim])
    n = 3 * cfg.patch * cfg.patch
    return rng.standard_normal((n, cfg.dim)) / np.sqrt(n)


def patch_descriptors(
    rgb: np.ndarray, cfg: DescriptorConfig = DescriptorConfig()
) -> tuple[FloatArray, FloatArray]:
    """Dense unit descriptors and local contrast of an RGB image.

    Args:
        rgb: (H, W, 3) uint8 image.
        cfg: descriptor parameters.

    Returns:
        D: (H, W, F) float32 descriptors with ``‖D‖ = 1`` per pixel (single precision, as a
            network's output; upstream refines matches with them in half precision).
        contrast: (H, W) float64 patch standard deviation (image values in [0, 1]).
    """
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb: expected uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if cfg.patch % 2 != 1 or cfg.patch < 1 or cfg.step < 1 or cfg.dim < 1:
        raise ValueError("cfg: patch must be odd and >= 1; step, dim >= 1")
    H, W = rgb.shape[:2]
    img = rgb.astype(np.float32) / np.float32(255.0)
    if cfg.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.blur_sigma, borderType=cv2.BORDER_REFLECT)
    r = (cfg.patch // 2) * cfg.step
    mode = "reflect" if min(H, W) > r else "edge"
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode=mode)
    w = 2 * r + 1
    win = sliding_window_view(pad, (w, w), axis=(0, 1))[..., :: cfg.step, :: cfg.step]
    P = _projection(cfg).astype(np.float32)
    n = P.shape[0]
    # The patch mean m and mean square: box sums over the same taps (of img and img²).
    mean, mean_sq = _tap_mean(pad, H, W, cfg), _tap_mean(pad * pad, H, W, cfg)
    contrast = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
    # P^T (z - m 1) = P^T z - m P^T 1, and the patch variance is mean(z²) - m².
    m32 = mean.astype(np.float32).reshape(-1, 1)
    inv = (1.0 / (contrast + cfg.eps)).astype(np.float32).reshape(-1, 1)
    P_sum = P.sum(axis=0)
    D = np.empty((H * W, cfg.dim), np.float32)
    # z (rows·W, 3p²) is built a few image rows at a time (the whole matrix would be 115 MB
    # at 512x384), and each block is finished while it is in cache: centred, scaled, unit norm.
    for y0 in range(0, H, _ROWS):
        z = np.ascontiguousarray(win[y0 : y0 + _ROWS].transpose(0, 1, 3, 4, 2)).reshape(-1, n)
        sl = slice(y0 * W, y0 * W + len(z))
        Db = np.matmul(z, P, out=D[sl])
        Db -= m32[sl] * P_sum
        Db *= inv[sl]
        Db[:, 0] += np.float32(1e-6)  # a fixed tiny offset keeps flat patches' norm above 0
        Db *= 1.0 / np.sqrt(np.einsum("nf,nf->n", Db, Db))[:, None]
    return D.reshape(H, W, cfg.dim), contrast


def _tap_mean(pad: np.ndarray, H: int, W: int, cfg: DescriptorConfig) -> np.ndarray:
    """(H, W) mean over the 3·p² taps of each pixel's patch, from the padded (H+2r, W+2r, 3)
    image, summed in float64: one p x p box filter for contiguous taps (``step`` 1), else a
    separable sum of p shifted rows, then p shifted columns."""
    r, s = (cfg.patch // 2) * cfg.step, cfg.step
    a = pad.astype(np.float64).sum(axis=2)
    if s == 1:
        box = cv2.boxFilter(
            a,
            -1,
            (cfg.patch, cfg.patch),
            anchor=(0, 0),
            normalize=False,
            borderType=cv2.BORDER_CONSTANT,
        )
        return box[:H, :W] / (3 * cfg.patch * cfg.patch)
    rows = sum(a[k : k + H] for k in range(0, 2 * r + 1, s))
    cols = sum(rows[:, k : k + W] for k in range(0, 2 * r + 1, s))
    return cols / (3 * cfg.patch * cfg.patch)
