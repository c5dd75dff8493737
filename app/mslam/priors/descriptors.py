"""Stand-in for MASt3R's local-feature head — dense patch descriptors from the image alone.

MASt3R predicts a 24-D unit descriptor per pixel (paper §3.2 uses it to refine matches in a
small window). Without the network, a fixed random projection of a normalised colour patch
plays that role: it is deterministic, identical for every image (so descriptors of two images
are comparable), varies smoothly with the pixel position (the image is blurred first and the
patch taps are spaced by ``step``), and discriminates between textured locations.

``D(u, v) = normalize(P^T z(u, v))`` with ``z`` the 3·p² samples of the blurred image on a p x p
grid of spacing ``step`` around (u, v), minus their mean and divided by their standard deviation
(plus ``eps``), and ``P`` a fixed (3p², F) random matrix. ``contrast(u, v)`` is that standard
deviation; :func:`descriptor_Q` turns it into the descriptor confidence
``Q = 1 + q_gain · tanh(contrast / q_contrast)`` (the network's Q of paper §3.1: at least 1,
saturating at ``1 + q_gain`` on textured patches), one formula for every prior.

Two kinds of ``P`` (``DescriptorConfig.kind``):

* ``"dense"``: every entry Gaussian. One (H·W, 3p²) x (3p², F) product: 0.7 GFLOP at 512x384.
* ``"separable"``: F/3 random separable p x p filters ``g_k ⊗ h_k`` (Gaussian taps, made to
  sum to zero along x or along y in turn), each applied to every colour channel on its own,
  so feature ``3k + c`` is filter k on channel c:
  ``P[(dy, dx, c), 3k + c'] = δ(c, c') g_k[dy] h_k[dx]``. Each filter is two 1-D passes
  (``cv2.sepFilter2D``), 2p instead of 3p² multiply-adds per pixel and feature: a 512x384
  frame takes about 18 ms instead of 54 (docs/system.md). The descriptors are still unit,
  smooth and discriminative; the matches they refine are measured in docs/system.md.

Public names, in reading order:
    DescriptorConfig, patch_descriptors, descriptor_Q
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from mslam_ref.conventions import FloatArray

__all__ = ["DescriptorConfig", "descriptor_Q", "patch_descriptors"]

#: Image rows per block of the patch matrix (bounds its memory at H-independent size).
_ROWS = 16


@dataclass(frozen=True)
class DescriptorConfig:
    """Patch descriptor parameters.

    Attributes:
        kind: "dense" or "separable" projection (module docstring).
        dim: descriptor dimension F (MASt3R: 24; a multiple of 3 for "separable").
        patch: p, taps per side (odd).
        step: spacing of the taps in pixels.
        blur_sigma: Gaussian blur of the image before sampling (pixels).
        eps: added to the patch standard deviation (flat patches stay finite).
        seed: seed of the projection matrix (the same for every image).
        cache_bytes: bound of the priors' per-frame cache (``mslam.priors.cache``).
    """

    kind: str = "dense"
    dim: int = 24
    patch: int = 7
    step: int = 1
    blur_sigma: float = 0.5
    eps: float = 0.02
    seed: int = 24
    cache_bytes: int = 128 * 2**20

    def __post_init__(self) -> None:
        if self.kind not in ("dense", "separable"):
            raise ValueError(f"kind: expected 'dense' or 'separable', got {self.kind!r}")
        if self.patch % 2 != 1 or self.patch < 1 or self.step < 1 or self.dim < 1:
            raise ValueError("patch must be odd and >= 1; step, dim >= 1")
        if self.kind == "separable" and self.dim % 3:
            raise ValueError(f"dim: a 'separable' descriptor needs a multiple of 3, got {self.dim}")


def _projection(cfg: DescriptorConfig) -> FloatArray:
    """``P`` (3p², F), rows ordered (dy, dx, colour) as the patch samples ``z``."""
    n = 3 * cfg.patch * cfg.patch
    if cfg.kind == "dense":
        rng = np.random.default_rng([cfg.seed, cfg.patch, cfg.dim])
        return rng.standard_normal((n, cfg.dim)) / np.sqrt(n)
    g, h = _separable_taps(cfg)
    P = np.einsum("ky,kx,cd->yxckd", g, h, np.eye(3))  # (p, p, 3, K, 3)
    return P.reshape(n, cfg.dim)


def _separable_taps(cfg: DescriptorConfig) -> tuple[FloatArray, FloatArray]:
    """(K, p) vertical taps ``g`` and horizontal taps ``h`` of the K = F/3 filters.

    Every filter sums to zero, ``h`` for even k and ``g`` for odd k (so that edges of both
    orientations register): ``P^T 1 = 0`` and the patch mean drops out of ``P^T (z - m 1)``.
    """
    rng = np.random.default_rng([cfg.seed, cfg.patch, cfg.dim, 3])
    g, h = rng.standard_normal((2, cfg.dim // 3, cfg.patch)) / np.sqrt(cfg.patch)
    if cfg.patch > 1:
        h[0::2] -= h[0::2].mean(axis=1, keepdims=True)
        g[1::2] -= g[1::2].mean(axis=1, keepdims=True)
    return g, h


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
    H, W = rgb.shape[:2]
    img: np.ndarray = rgb.astype(np.float32) / np.float32(255.0)
    if cfg.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.blur_sigma, borderType=cv2.BORDER_REFLECT)
    r = (cfg.patch // 2) * cfg.step
    # Taps outside the image mirror it (np.pad "reflect"), or repeat the edge when it is tiny.
    border = cv2.BORDER_REFLECT_101 if min(H, W) > r else cv2.BORDER_REPLICATE
    # The patch mean m and mean square: box sums over the same taps (of img and img²).
    mean, mean_sq = _tap_mean(img, cfg, border), _tap_mean(img * img, cfg, border)
    contrast = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
    # Scaling P^T (z - m 1) by 1 / (contrast + eps) only sizes the fixed tiny offset that keeps
    # a flat patch's norm above 0 (1e-6 on the first feature), as the result is made unit.
    offset = (1e-6 * (contrast + cfg.eps)).astype(np.float32).reshape(-1)
    if cfg.kind == "dense":
        D = _dense(img, mean, offset, cfg, border)
    else:
        D = _separable(img, offset, cfg, border)
    return D.reshape(H, W, cfg.dim), contrast


def descriptor_Q(contrast: FloatArray, q_gain: float, q_contrast: float) -> FloatArray:
    """Descriptor confidence Q of the patch descriptors, from their contrast.

    Paper §3.1 (the network's Q; tracking and the backend keep matches with ``Q > Q_conf``).
    ``Q = 1 + q_gain · tanh(contrast / q_contrast)``: flat patches get ``Q = 1``, textured ones
    approach ``1 + q_gain``, monotone in the contrast.

    Args:
        contrast: (...) patch standard deviation from :func:`patch_descriptors`.
        q_gain: ``Q - 1`` of a fully textured patch (>= 0).
        q_contrast: contrast scale of the saturation (> 0).

    Returns:
        (...) float64 Q, >= 1.
    """
    return 1.0 + q_gain * np.tanh(contrast / q_contrast)


def _dense(
    img: np.ndarray, mean: FloatArray, offset: np.ndarray, cfg: DescriptorConfig, border: int
) -> np.ndarray:
    """(H·W, F) unit ``P^T (z - m 1) + offset e_0`` with the Gaussian ``P``: the patch matrix
    z (rows·W, 3p²) is built a few image rows at a time (the whole matrix would be 115 MB at
    512x384), and each block is finished while it is in cache."""
    H, W = img.shape[:2]
    r = (cfg.patch // 2) * cfg.step
    mode: Literal["reflect", "edge"] = "reflect" if border == cv2.BORDER_REFLECT_101 else "edge"
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode=mode)
    win = sliding_window_view(pad, (2 * r + 1, 2 * r + 1), axis=(0, 1))
    win = win[..., :: cfg.step, :: cfg.step]
    P = _projection(cfg).astype(np.float32)
    P_sum = P.sum(axis=0)  # P^T (z - m 1) = P^T z - m P^T 1
    m32 = mean.astype(np.float32).reshape(-1, 1)
    D = np.empty((H * W, cfg.dim), np.float32)
    for y0 in range(0, H, _ROWS):
        z = np.ascontiguousarray(win[y0 : y0 + _ROWS].transpose(0, 1, 3, 4, 2))
        sl = slice(y0 * W, y0 * W + z.shape[0] * W)
        Db = np.matmul(z.reshape(-1, P.shape[0]), P, out=D[sl])
        Db -= m32[sl] * P_sum
        Db[:, 0] += offset[sl]
        Db *= 1.0 / np.sqrt(np.einsum("nf,nf->n", Db, Db))[:, None]
    return D


def _separable(
    img: np.ndarray, offset: np.ndarray, cfg: DescriptorConfig, border: int
) -> np.ndarray:
    """(H·W, F) unit ``P^T z + offset e_0`` (= ``P^T (z - m 1)``: the filters sum to zero)
    with the separable ``P``: filter k on the three channels at once (one
    ``cv2.sepFilter2D``)."""
    H, W = img.shape[:2]
    g, h = _dilated(_separable_taps(cfg), cfg.step)
    out = [cv2.sepFilter2D(img, cv2.CV_32F, h_k, g_k, borderType=border) for g_k, h_k in zip(g, h)]
    out[0][..., 0] += offset.reshape(H, W)
    D = cv2.merge(out).reshape(H * W, cfg.dim)  # feature 3k + c: filter k on channel c
    D *= 1.0 / np.sqrt(np.einsum("nf,nf->n", D, D))[:, None]
    return D


def _dilated(taps: tuple[FloatArray, ...], step: int) -> list[FloatArray]:
    """(K, p) taps as (K, (p-1)·step + 1) kernels with zeros between the taps."""
    out = []
    for t in taps:
        k = np.zeros((t.shape[0], (t.shape[1] - 1) * step + 1), np.float32)
        k[:, ::step] = t
        out.append(k)
    return out


def _tap_mean(a3: np.ndarray, cfg: DescriptorConfig, border: int) -> np.ndarray:
    """(H, W) float64 mean over the 3·p² taps of each pixel's patch, of an (H, W, 3) image:
    one p x p box filter of the channel sum (a dilated one when ``step`` > 1)."""
    a = cv2.transform(a3.astype(np.float64), np.ones((1, 3)))  # channel sum (numpy's is slow)
    p = cfg.patch
    if cfg.step == 1:
        box = cv2.boxFilter(a, -1, (p, p), normalize=False, borderType=border)
    else:
        taps = np.zeros((p - 1) * cfg.step + 1)
        taps[:: cfg.step] = 1.0
        box = cv2.sepFilter2D(a, cv2.CV_64F, taps, taps, borderType=border)
    return box / (3 * p * p)
