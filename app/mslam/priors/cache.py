"""A least-recently-used cache bounded in bytes, for per-frame results of the priors.

The priors cache per-frame work (patch descriptors, features, flows, encoder features)
because a frame is paired with several keyframes. Every prior (synthetic, RGB-D, two-view,
MASt3R) keeps it in a :class:`ByteLRU` bounded by its config's ``cache_bytes``. An entry's
size is the sum of the ``nbytes`` of the arrays it holds (NumPy arrays, and tensors that
report ``nbytes``, descending into tuples, lists and dicts), so the bound holds at every
resolution, which a bound on the number of entries does not: patch descriptors alone take
H·W·104 bytes per frame (8 MB at 320x240, 20 MB at 512x384).

:meth:`ByteLRU.compute_alongside` computes missing entries on a worker thread while the caller
does other work (the RGB-D prior finds a frame's keypoints, in OpenCV, which releases the GIL,
while it computes the frame's descriptors).

Public names: DEFAULT_CACHE_BYTES, ByteLRU, nbytes.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping
from typing import Any, TypeVar

import numpy as np

__all__ = ["DEFAULT_CACHE_BYTES", "ByteLRU", "nbytes"]

#: Default bound of a prior's per-frame cache: 128 MiB (about 34 frames of descriptors at
#: 160x120, 4 at 512x384).
DEFAULT_CACHE_BYTES = 128 * 2**20

#: A cache key type (the priors use tuples).
_Key = TypeVar("_Key", bound=Hashable)


def nbytes(value: Any) -> int:
    """Bytes held by the arrays in ``value`` (recursing into containers): NumPy arrays and
    any other array type with an integer ``nbytes`` (torch tensors); 0 for everything else."""
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, str | bytes | int | float | bool | np.generic) or value is None:
        return 0
    if isinstance(value, tuple | list):
        return sum(nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(nbytes(v) for v in value.values())
    size = getattr(value, "nbytes", None)
    return int(size) if isinstance(size, int | np.integer) and not isinstance(size, bool) else 0


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

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def keys(self) -> list[Hashable]:
        """The cached keys, least recently used first."""
        return list(self._items)

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The value of ``key``, computing and storing it on a miss."""
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key][0]
        value = compute()
        self.put(key, value)
        return value

    def put(self, key: Hashable, value: Any) -> None:
        """Store ``value`` under ``key`` (replacing an earlier value) as the most recent entry,
        then evict least recently used entries down to the bound."""
        self.pop(key)
        size = nbytes(value)
        if size <= self.max_bytes:
            self._items[key] = (value, size)
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, (_, old) = self._items.popitem(last=False)
                self.bytes -= old

    def peek(self, key: Hashable, default: Any = None) -> Any:
        """The value of ``key`` (``default`` on a miss) without making it the most recent."""
        item = self._items.get(key)
        return default if item is None else item[0]

    def pop(self, key: Hashable, default: Any = None) -> Any:
        """Remove ``key``; its value, or ``default`` when it is not cached."""
        item = self._items.pop(key, None)
        if item is None:
            return default
        self.bytes -= item[1]
        return item[0]

    def clear(self) -> None:
        """Remove every entry."""
        self._items.clear()
        self.bytes = 0

    def compute_alongside(self, jobs: Mapping[_Key, Callable[[], Any]]) -> Callable[..., None]:
        """Start computing the jobs whose keys are not cached, in order, on a worker thread.

        Returns ``join(*keys)``: waits until those jobs (all of them when no key is given) are
        done and stores their values, re-raising the worker's exception, if any, in the
        caller's thread. The cache itself is touched by the caller's thread only.
        """
        todo = {k: fn for k, fn in jobs.items() if k not in self._items}
        done = {k: threading.Event() for k in todo}
        out: dict[Hashable, Any] = {}
        failed: list[BaseException] = []

        def work() -> None:
            for key, fn in todo.items():
                try:
                    if not failed:
                        out[key] = fn()
                except BaseException as exc:  # handed to the caller by join
                    failed.append(exc)
                finally:
                    done[key].set()

        if todo:
            threading.Thread(target=work, name="cache-alongside", daemon=True).start()

        def join(*keys: Hashable) -> None:
            for key in keys or tuple(todo):
                if key in done:
                    done[key].wait()
            if failed:
                raise failed[0]
            for key in keys or tuple(todo):
                if key in out:
                    self.get(key, _returning(out.pop(key)))

        return join


def _returning(value: Any) -> Callable[[], Any]:
    """A ``compute`` for :meth:`ByteLRU.get` that returns the already computed ``value``."""
    return lambda: value
