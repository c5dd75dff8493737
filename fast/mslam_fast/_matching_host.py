"""Host-side argument preparation of ``mslam_fast.matching``: dtype conversion, finiteness
checks and the zero-padded scratch arrays of the refinement kernel."""

import threading
from typing import Any

import numpy as np

from mslam_fast._runtime import ensure_init, generation

Array = np.ndarray[Any, Any]

_PAD = 8  # descriptor padding of F to a multiple of 8 (see scratch)


def all_finite(arr: Array) -> bool:
    """True when no entry is NaN or ±inf: ``max`` propagates NaN and shows +inf, ``min`` shows
    -inf. Two vectorised passes, 4x faster than a float64 sum for 512x384x24 float32
    descriptors (0.5 against 2 ms)."""
    return arr.size == 0 or bool(np.isfinite(arr.max()) and np.isfinite(arr.min()))


def as_runtime_float(x: Any, name: str) -> Array:
    """Contiguous runtime-dtype copy/view of a finite array (ValueError naming ``name``)."""
    arr = np.ascontiguousarray(x, dtype=ensure_init().dtype)
    if not all_finite(arr):
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
    if not all_finite(x):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return x


def scratch(B: int, H: int, W: int, F: int, N: int, pad: int) -> tuple[Any, Any]:
    """Zeroed runtime-type scratch: image-1 descriptors with a border of ``pad`` zero pixels,
    as rows ``(B·(H + 2 pad)·(W + 2 pad), Fp)``, and target rows ``(B·N, Fp)``; F zero-padded to
    a multiple of 8 (one AVX register of f32) for the vectorised dot products (24 stays 24;
    padding to 32 measured ~10-20 % slower).

    The last pair is kept per thread and shape: the kernels never write the border or the
    padding columns, and read a row only after writing it in the same call, so a kept pair
    stays valid. Fresh zeroed pages cost the first write of each page: 77 MB per 512x384 call
    in float64, 15-30 ms of a ~80 ms match on the 2-core machine (at 160x120 it was noise).
    On CUDA they are Taichi ndarrays in GPU memory, which the kernels use in place: as NumPy
    arrays they were copied to the GPU and back at every call.
    """
    Fp = -(-F // _PAD) * _PAD
    rows = (B * (H + 2 * pad) * (W + 2 * pad), Fp), (B * N, Fp)
    return _kept(("scratch", B, H, W, F, N, pad), lambda: tuple(_zeros(r) for r in rows))


def ray_scratch(B: int, H: int, W: int) -> Any:
    """The (B, H, W, 9) runtime-type image of unit rays and their gradients, which the kernel
    writes whole each call before reading it; kept per thread and shape like :func:`scratch`."""
    return _kept(("rays", B, H, W), lambda: _zeros((B, H, W, 9)))


_KEPT = threading.local()


def _zeros(shape: tuple[int, ...]) -> Any:
    """A zeroed runtime-type array: NumPy on the CPU, a ``ti.ndarray`` on the GPU."""
    rt = ensure_init()
    if rt.arch == "cpu" or 0 in shape:  # Taichi has no empty ndarrays (an empty batch)
        return np.zeros(shape, rt.dtype)
    import taichi as ti

    a = ti.ndarray(ti.f64 if rt.fp == "f64" else ti.f32, shape)
    a.fill(0)
    return a


def _kept(key: tuple, make: Any) -> Any:
    """This thread's last value for ``key[0]`` if it was made for ``key`` under the current
    runtime (arch, precision and Taichi initialisation), else ``make()``, kept."""
    rt = ensure_init()
    key = (*key, rt.arch, rt.fp, generation())
    kept = getattr(_KEPT, key[0], None)
    if kept is None or kept[0] != key:
        kept = (key, make())
        setattr(_KEPT, key[0], kept)
    return kept[1]


def flags(a: Array) -> Array:
    return a.view(np.bool_)
