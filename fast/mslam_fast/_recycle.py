"""Large output arrays recycled once their caller has let go of them.

A fast twin returns new NumPy arrays, as its reference does. Fresh memory is expensive on the
2-core machine, though: the first write of each page faults, and a kernel that writes a fresh
120 MB array (the bundle adjuster's ``W`` at the KITTI-00 size) measured 27-165 ms of CPU time
against 15 ms into memory written before (2026-11-26). :func:`output` therefore hands out the
array that the same call site returned last, when nobody holds it any more: no variable, no
view, no container refers to it (its reference count shows only this module's). An array a
caller still holds is never reused, so a returned array is the caller's for as long as it keeps
it, exactly as a fresh one.

At most one array per call site and thread stays allocated between calls.

Public names: output.
"""

import sys
import threading
from typing import Any

import numpy as np

__all__ = ["output"]

Array = np.ndarray[Any, Any]

_POOL = threading.local()
#: ``sys.getrefcount`` of a pooled array nobody else holds: the pool's entry, the local name in
#: :func:`output` and the call's own argument.
_FREE_REFS = 3


def output(key: str, shape: tuple[int, ...], dtype: Any) -> Array:
    """An uninitialised ``shape`` array of ``dtype`` for the output ``key``: the last one made
    for ``key`` on this thread when it has that shape and dtype and nothing else refers to it,
    else a new one (which replaces it in the pool). The caller's kernel must write every
    element."""
    pool = _POOL.__dict__
    arr = pool.get(key)
    if (
        arr is not None
        and arr.shape == shape
        and arr.dtype == dtype
        and sys.getrefcount(arr) == _FREE_REFS
    ):
        return arr
    arr = np.empty(shape, dtype)
    pool[key] = arr
    return arr
