"""A least-recently-used cache bounded in bytes, for per-frame results of the priors.

The priors cache per-frame work (patch descriptors, features) because a frame is paired with
several keyframes. An entry's size is the sum of the ``nbytes`` of the NumPy arrays it holds
(descending into tuples, lists and dicts), so the bound holds at every resolution: a count
bound (the earlier 64 entries) grows with H·W·192 bytes per frame (943 MB at 320x240).

Public names: DEFAULT_CACHE_BYTES, ByteLRU, nbytes.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

__all__ = ["DEFAULT_CACHE_BYTES", "ByteLRU", "nbytes"]

#: Default bound of a prior's per-frame cache: 128 MiB (about 34 frames of descriptors at
#: 160x120, 4 at 512x384).
DEFAULT_CACHE_BYTES = 128 * 2**20


def nbytes(value: Any) -> int:
    """Bytes held by the NumPy arrays in ``value`` (recursing into containers)."""
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, tuple | list):
        return sum(nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(nbytes(v) for v in value.values())
    return 0


class ByteLRU:
    """``get(key, compute)``: the cached value, or ``compute()`` stored; least recently used
    entries are evicted while the total exceeds ``max_bytes`` (an entry larger than the bound
    is returned but not kept)."""

    def __init__(self, max_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        if (
            isinstance(max_bytes, bool)
            or not isinstance(max_bytes, int | np.integer)
            or max_bytes < 0
        ):
            raise ValueError(f"max_bytes: expected an int >= 0, got {max_bytes!r}")
        self.max_bytes = int(max_bytes)
        self.bytes = 0
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The value of ``key``, computing and storing it on a miss."""
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key][0]
        value = compute()
        size = nbytes(value)
        if size <= self.max_bytes:
            self._items[key] = (value, size)
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, (_, old) = self._items.popitem(last=False)
                self.bytes -= old
        return value
