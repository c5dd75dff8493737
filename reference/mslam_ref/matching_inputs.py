"""Input checks of pointmap matching, shared by ``mslam_ref.matching`` and its fast twin.

Shapes only (and integer pixels inside the image): the values are sanitised where they are
used (non-finite points become "no point", descriptors must be finite). Every check raises
``ValueError`` naming the argument.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["check_match_inputs", "image_batch", "int_pixels"]


def image_batch(x: Any, name: str, channels: int | None) -> tuple[FloatArray, bool]:
    """Return ``x`` as (B, H, W, C) and whether it had a batch axis; H, W >= 3, C >= 1.

    Numbers only: a boolean array is an error; integer arrays become float64 here, once, for
    the reference and the fast twin alike.
    """
    arr = np.asarray(x)
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    if np.issubdtype(arr.dtype, np.integer):
        arr = arr.astype(np.float64)
    if arr.ndim >= 1 and arr.shape[-1] == 0:
        raise ValueError(f"{name}: zero-length last axis (no coordinates or descriptor entries)")
    if arr.ndim not in (3, 4) or (channels is not None and arr.shape[-1] != channels):
        want = f"(H, W, {channels or 'F'})"
        raise ValueError(f"{name}: expected shape {want} or (B, *{want}), got {arr.shape}")
    if arr.shape[-3] < 3 or arr.shape[-2] < 3:
        raise ValueError(f"{name}: images must be at least 3x3 pixels, got shape {arr.shape}")
    batched = arr.ndim == 4
    return (arr if batched else arr[None]), batched


def int_pixels(p: Any, name: str, shape: tuple[int, ...], H: int, W: int) -> IntArray:
    """Check an integer pixel array of ``shape`` inside [0, W) x [0, H); return int64."""
    arr = np.asarray(p)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: expected integer pixels, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    u, v = arr[..., 0], arr[..., 1]
    if np.any((u < 0) | (u >= W) | (v < 0) | (v >= H)):
        raise ValueError(f"{name}: pixels must lie inside the {W}x{H} image")
    return arr


def check_match_inputs(X11: Any, X21: Any, D11: Any, D21: Any, idx_init: Any) -> tuple:
    """Shape checks of ``mslam_ref.matching.match`` (shared with the fast twin): returns the four inputs as
    (B, H, W, C) arrays (not converted), ``idx_init`` as (B, N) int64 or None, and the flag."""
    X1, batched = image_batch(X11, "X11", 3)
    X2, batched2 = image_batch(X21, "X21", 3)
    if X2.shape != X1.shape or batched2 != batched:
        raise ValueError(f"X21: expected the shape of X11 {np.shape(X11)}, got {np.shape(X21)}")
    D1, b1 = image_batch(D11, "D11", None)
    D2, b2 = image_batch(D21, "D21", None)
    if D1.shape[:-1] != X1.shape[:-1] or b1 != batched:
        raise ValueError(f"D11: expected shape {(*np.shape(X11)[:-1], 'F')}, got {np.shape(D11)}")
    if D2.shape != D1.shape or b2 != batched:
        raise ValueError(f"D21: expected the shape of D11 {np.shape(D11)}, got {np.shape(D21)}")
    B, H, W, _ = X1.shape
    if idx_init is None:
        return X1, X2, D1, D2, None, batched
    idx = np.asarray(idx_init)
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"idx_init: expected integer indices, got dtype {idx.dtype}")
    if idx.shape != ((B, H * W) if batched else (H * W,)):
        raise ValueError(f"idx_init: expected shape (B, N) or (N,), N={H * W}, got {idx.shape}")
    idx = np.ascontiguousarray(idx, dtype=np.int64).reshape(B, H * W)
    if idx.size and (idx.min() < 0 or idx.max() >= H * W):
        raise ValueError(f"idx_init: indices must lie in [0, {H * W})")
    return X1, X2, D1, D2, idx, batched
