"""Device arrays of the resident entries (``mslam_fast.resident``): upload counting, the
storage policy, uploads and downloads, and :class:`Kept`, the device form of one read-only host
array.

Under ``numpy`` storage (the CPU) a device array is the host array itself; under ``ndarray``
storage (CUDA, or the CPU inside :func:`ndarrays_on_cpu`) it is a ``ti.ndarray``.
"""

from __future__ import annotations

import contextlib
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from mslam_fast._runtime import ensure_init, generation

__all__ = [
    "Kept",
    "empty",
    "ndarrays_on_cpu",
    "reset_uploads",
    "storage",
    "to_device",
    "to_host",
    "uploads",
]

Array = np.ndarray[Any, Any]

_UPLOADS: Counter[str] = Counter()
_LOCK = threading.Lock()
_FORCE_NDARRAY = threading.local()


def uploads() -> dict[str, int]:
    """Uploads so far, by label (``"matching.D21"``, ``"tracking.X_k"``, ...)."""
    with _LOCK:
        return dict(_UPLOADS)


def reset_uploads() -> None:
    """Set every upload count to zero."""
    with _LOCK:
        _UPLOADS.clear()


def storage() -> str:
    """``"ndarray"`` (Taichi device arrays: on CUDA, or on the CPU inside
    :func:`ndarrays_on_cpu`) or ``"numpy"`` (the CPU: a device array is the host array)."""
    if ensure_init().arch != "cpu" or getattr(_FORCE_NDARRAY, "on", False):
        return "ndarray"
    return "numpy"


@contextlib.contextmanager
def ndarrays_on_cpu() -> Iterator[None]:
    """In this thread, keep device arrays as ``ti.ndarray``s on the CPU too (CUDA's code path)."""
    before = getattr(_FORCE_NDARRAY, "on", False)
    _FORCE_NDARRAY.on = True
    try:
        yield
    finally:
        _FORCE_NDARRAY.on = before


_TI_TYPES = {"float64": "f64", "float32": "f32", "int64": "i64", "uint8": "u8"}


def empty(shape: tuple[int, ...], dtype: Any) -> Any:
    """Uninitialised device array (NumPy under ``numpy`` storage)."""
    if storage() == "numpy" or 0 in shape:  # Taichi has no empty ndarrays
        return np.empty(shape, dtype)
    import taichi as ti

    return ti.ndarray(getattr(ti, _TI_TYPES[np.dtype(dtype).name]), shape)


def to_device(a: Array, label: str) -> Any:
    """The device copy of the contiguous host array ``a`` (``a`` itself under ``numpy``
    storage), counted as one upload under ``label``."""
    with _LOCK:
        _UPLOADS[label] += 1
    a = np.ascontiguousarray(a)
    if storage() == "numpy" or a.size == 0:
        return a
    d = empty(a.shape, a.dtype)
    d.from_numpy(a)
    return d


def to_host(d: Any) -> Array:
    """A host array of the device array ``d`` (``d`` itself when it is one already)."""
    return d if isinstance(d, np.ndarray) else d.to_numpy()


def _trusted(a: Any) -> bool:
    """A read-only NumPy array: its owner promises that it does not change (the priors mark
    their cached per-frame arrays so)."""
    return isinstance(a, np.ndarray) and not a.flags.writeable


class Kept:
    """The device form of one host array, kept while the same read-only object comes back.

    ``get(a, make)`` returns the kept value when ``a`` is the object it was made from (and
    the storage and Taichi initialisation are unchanged), else ``make(a)``, kept when ``a`` is
    read-only. ``made`` counts the calls of ``make``.
    """

    def __init__(self) -> None:
        self._source: Any = None
        self._key: tuple[Any, ...] = ()
        self._value: Any = None
        self.made = 0

    def get(self, a: Any, make: Callable[[Any], Any]) -> Any:
        rt = ensure_init()
        key = (rt.arch, rt.fp, storage(), generation())
        if self._source is not None and a is self._source and key == self._key:
            return self._value
        value = make(a)
        self.made += 1
        if _trusted(a):
            self._source, self._key, self._value = a, key, value
        else:
            self.clear()
        return value

    def clear(self) -> None:
        """Forget the kept value."""
        self._source, self._key, self._value = None, (), None
