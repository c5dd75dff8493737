"""Image operations of pointmap matching: Scharr gradients and bilinear sampling.

Both act on (..., H, W, C) images with channels last, in float64, and are written as
whole-image array expressions. ``mslam_ref.matching`` re-exports them (it uses them for the ray
image and for every LM step); the fast twin has them inside its kernels
(``mslam_fast._kernels.matching.scharr_at``, ``sample9``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_ref.conventions import FloatArray, as_float_array

__all__ = ["bilinear_sample", "scharr_gradients"]


def scharr_gradients(img: Any) -> tuple[FloatArray, FloatArray]:
    """Scharr-type image gradients per channel with reflect padding, as cross-correlation.

    Upstream: image.py::img_gradient (F.pad reflect 1 px, F.conv2d per channel).

        gx = (1/32) [[-3, 0, 3], [-10, 0, 10], [-3, 0, 3]]   ⋆ img
        gy = (1/32) [[-3, -10, -3], [0, 0, 0], [3, 10, 3]]   ⋆ img

    On a linear ramp ``img = a u + b v`` the interior gradients are exactly (a, b).

    Args:
        img: (..., H, W, C) image, H, W >= 2.

    Returns:
        gx, gy: (..., H, W, C) float64 derivatives along u (columns) and v (rows).
    """
    img = as_float_array(img, "img")
    if img.ndim < 3 or img.shape[-3] < 2 or img.shape[-2] < 2:
        raise ValueError(f"img: expected (..., H, W, C) with H, W >= 2, got shape {img.shape}")
    pad = [(0, 0)] * (img.ndim - 3) + [(1, 1), (1, 1), (0, 0)]
    P = np.pad(img, pad, mode="reflect")
    H, W = img.shape[-3], img.shape[-2]

    def tap(dv: int, du: int) -> FloatArray:  # P at (v + dv, u + du) for every pixel (v, u)
        return P[..., 1 + dv : 1 + dv + H, 1 + du : 1 + du + W, :]

    gx = (
        3.0 * (tap(-1, 1) - tap(-1, -1))
        + 10.0 * (tap(0, 1) - tap(0, -1))
        + 3.0 * (tap(1, 1) - tap(1, -1))
    ) / 32.0
    gy = (
        3.0 * (tap(1, -1) - tap(-1, -1))
        + 10.0 * (tap(1, 0) - tap(-1, 0))
        + 3.0 * (tap(1, 1) - tap(-1, 1))
    ) / 32.0
    return gx, gy


def bilinear_sample(img: Any, u: Any, v: Any) -> FloatArray:
    """Bilinear interpolation of an image at sub-pixel positions inside [0, W−1) × [0, H−1).

    Upstream: matching_kernels.cu::bilinear_interp. With u0 = ⌊u⌋, du = u − u0 (same for v):

        I(u, v) = (1−du)(1−dv) I[v0, u0] + du (1−dv) I[v0, u0+1]
                + (1−du) dv I[v0+1, u0] + du dv I[v0+1, u0+1]

    Args:
        img: (H, W, C) or (B, H, W, C) image.
        u, v: (N,) or (B, N) positions with 0 <= u <= W−2, 0 <= v <= H−2 (the LM's clamp
            guarantees it).

    Returns:
        (N, C) or (B, N, C) float64 samples.
    """
    img = np.asarray(img, dtype=np.float64)
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if img.ndim == 3:
        return bilinear_sample(img[None], u[None], v[None])[0]
    if img.ndim != 4 or u.shape != v.shape or u.shape[:1] != img.shape[:1] or u.ndim != 2:
        raise ValueError(
            f"img, u, v: expected (B, H, W, C), (B, N), (B, N); got {img.shape}, "
            f"{u.shape}, {v.shape}"
        )
    B, H, W, C = img.shape
    if np.any(~(u >= 0) | (u > W - 2) | ~(v >= 0) | (v > H - 2)):
        raise ValueError("u, v: positions must lie in [0, W-2] x [0, H-2]")
    flat = img.reshape(B, H * W, C)
    u0, v0 = np.floor(u), np.floor(v)
    du, dv = (u - u0)[..., None], (v - v0)[..., None]
    i00 = u0.astype(np.int64) + W * v0.astype(np.int64)
    b = np.arange(B)[:, None]
    return (
        (1.0 - du) * (1.0 - dv) * flat[b, i00]
        + du * (1.0 - dv) * flat[b, i00 + 1]
        + (1.0 - du) * dv * flat[b, i00 + W]
        + du * dv * flat[b, i00 + W + 1]
    )
