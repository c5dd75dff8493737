"""Paper §3.5 (docs/upstream.md §1.5) — the backend in a background thread (``single_thread: False``).

Upstream runs the backend (graph construction for each new keyframe, then the global solve)
in its own process and lets the frontend go on tracking meanwhile. By default this
implementation runs that step synchronously after every new keyframe, so that a run is a pure
function of its input; with ``single_thread: False`` (``--set single_thread=false``) a
:class:`BackendWorker` thread runs it instead, one keyframe after the other, while the
frontend tracks the next frames against the poses the backend has written so far.

What is shared, and how:

* keyframe list, poses and pointmaps — ``Backend.lock`` (an ``RLock``) guards appending a
  keyframe, replacing a pointmap and the backend's snapshot and write-back of the poses;
* the prior — :class:`SharedPrior` serialises ``pair``/``mono`` (its per-frame caches are not
  thread-safe) and keeps ``last_status`` per thread, so the frontend reads its own pair's status;
* relocalisation and the end of the run first wait until the worker has finished every
  queued keyframe (``BackendWorker.drain``).

Taichi kernels hold the GIL while they run and OpenCV/BLAS calls release it, so the two
threads overlap where one of them is in OpenCV or BLAS; on 2 cores the gain is modest
(benchmarks/RESULTS.md, "Background backend"). Runs with the worker are not deterministic:
when a solve lands depends on the thread schedule. An error in the worker is raised in the
frontend at its next ``submit`` or ``drain``.

Public names, in reading order:
    SharedPrior, BackendWorker
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Any

from mslam.datasets.frame import Frame
from mslam.priors.base import PairPrediction, Prior
from mslam.system.edges import KnownPairs
from mslam_ref.conventions import FloatArray

__all__ = ["BackendWorker", "SharedPrior"]


class SharedPrior:
    """A prior used by two threads: calls serialised, ``last_status`` kept per thread.

    Every other attribute is the wrapped prior's.
    """

    def __init__(self, prior: Prior) -> None:
        self._prior = prior
        self._lock = threading.Lock()
        self._local = threading.local()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._prior, name)

    @property
    def last_status(self) -> str:
        """Status of this thread's last ``pair`` call ("ok" for priors that report none)."""
        return getattr(self._local, "status", "ok")

    def pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        """The wrapped prior's ``pair``, one thread at a time."""
        with self._lock:
            out = self._prior.pair(frame_i, frame_j)
            self._local.status = getattr(self._prior, "last_status", "ok")
        return out

    def mono(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """The wrapped prior's ``mono``, one thread at a time."""
        with self._lock:
            return self._prior.mono(frame)


class BackendWorker:
    """Runs ``step(k, known)`` for each submitted keyframe in a daemon thread, in order.

    Args:
        step: the work for one new keyframe (``Backend.step``).
    """

    def __init__(self, step: Callable[[int, KnownPairs | None], None]) -> None:
        self._step = step
        self._queue: queue.Queue[tuple[int, KnownPairs] | None] = queue.Queue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="mslam-backend", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if self._error is None:
                    self._step(*item)
            except BaseException as exc:  # handed to the frontend thread
                self._error = exc
            finally:
                self._queue.task_done()

    def _raise(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise RuntimeError(f"background backend failed: {error}") from error

    @property
    def alive(self) -> bool:
        """Whether the worker thread still runs (False once closed)."""
        return self._thread.is_alive()

    def submit(self, k: int, known: KnownPairs | None = None) -> None:
        """Queue keyframe ``k``'s graph step and solve (``known``: decodes to reuse)."""
        self._raise()
        if not self._thread.is_alive():
            raise RuntimeError("background backend: the worker has been closed")
        self._queue.put((int(k), known or {}))

    def drain(self) -> None:
        """Wait until every queued keyframe has been processed."""
        self._queue.join()
        self._raise()

    def close(self) -> None:
        """Drain, then stop the thread."""
        if self._thread.is_alive():
            self._queue.join()
            self._queue.put(None)
            self._thread.join()
        self._raise()
