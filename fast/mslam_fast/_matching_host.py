"""Host-side argument preparation of ``mslam_fast.matching``: dtype conversion, finiteness
checks and the zero-padded scratch arrays of the refinement kernel."""

from typing import Any

import numpy as np

from mslam_fast._runtime import ensure_init

Array = np.ndarray[Any, Any]

_PAD = 8  # descriptor padding of F to a multiple of 8 (see scratch)


def as_runtime_float(x: Any, name: str) -> Array:
    """Contiguous runtime-dtype copy/view of a finite array (ValueError naming ``name``)."""
    arr = np.ascontiguousarray(x, dtype=ensure_init().dtype)
    # one cheap reduction first; the element-wise check only when the sum is not finite
    if arr.size and not np.isfinite(arr.sum(dtype=np.float64)) and not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return arr


def points(x: Any) -> Array:
    """Contiguous runtime-dtype points with non-finite points zeroed (as the reference)."""
    arr = np.ascontiguousarray(x, dtype=ensure_init().dtype)
    bad = ~np.isfinite(arr)
    if bad.any():
        arr = arr.copy()
        arr[bad.any(axis=-1)] = 0.0
    return arr


def descriptors(x: Any, name: str) -> Array:
    """Finite descriptors as a contiguous float array, not copied when already one.

    The kernel itself casts them to the runtime type into zero-padded scratch arrays
    (:func:`scratch`), in parallel, so the host does no per-element work but the finiteness check.
    """
    x = np.asarray(x)
    if x.dtype not in (np.float32, np.float64):
        x = x.astype(ensure_init().dtype)
    x = np.ascontiguousarray(x)
    if x.size and not np.isfinite(x.sum(dtype=np.float64)) and not np.isfinite(x).all():
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return x


def scratch(B: int, H: int, W: int, F: int, N: int, pad: int) -> tuple[Array, Array]:
    """Zeroed runtime-type scratch: image-1 descriptors with a border of ``pad`` zero pixels,
    as rows ``(B·(H + 2 pad)·(W + 2 pad), Fp)``, and target rows ``(B·N, Fp)``; F zero-padded to
    a multiple of 8 (one AVX register of f32) for the vectorised dot products (24 stays 24;
    padding to 32 measured ~10-20 % slower). (Keeping these arrays between calls of one shape
    was measured: no gain above the noise, so they are fresh each call.)"""
    Fp = -(-F // _PAD) * _PAD
    dt = ensure_init().dtype
    return np.zeros((B * (H + 2 * pad) * (W + 2 * pad), Fp), dt), np.zeros((B * N, Fp), dt)


def flags(a: Array) -> Array:
    return a.view(np.bool_)
