"""The next frame's flow to its keyframe, computed while the current frame is tracked.

The frame loop (``mslam.system.run``) reads frame t + 1 before it processes frame t and hands
it to :meth:`mslam.priors.twoview.TwoViewPrior.prefetch` together with the frame it will
most likely be paired with: the last keyframe (``SlamSystem.pair_partner``). A worker
thread then computes what depends on those two images alone — the frame's patch
descriptors, its SIFT keypoints when the flow needs its guide, and the dense flow both ways
(:func:`mslam.priors.twoview_flow.guided_flow`) — while the main thread matches, tracks and
solves frame t. The pose of the pair is not prefetched: it depends on the depths remembered
from earlier pairs (the third view), which frame t may still change.

The worker never touches the prior's cache: the caller's thread looks up what is already
cached before the worker starts and stores the worker's results when the pair is asked for
(:meth:`FlowPrefetch.settle`), at the next prefetch or at :meth:`FlowPrefetch.join`. The
same functions run on the same images, so the values are those computed on demand and the
trajectory is the same bit for bit (tests/app/test_twoview_prefetch.py). When frame t becomes
a keyframe, frame t + 1 is paired with it instead and the prefetched flow is not used (it may
still serve a later pair of the same two images). A failed step is dropped: it runs again,
and raises, when its result is asked for.

DIS and SIFT (OpenCV) release the GIL, so on two cores they overlap the main thread's
single-threaded Python (the pose refinement, the graph): benchmarks/RESULTS.md, "The next
frame's flow beside the current frame".

Public names: FlowPrefetch, pair_keys, pair_work
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Hashable
from typing import Any

from mslam.datasets.frame import Frame
from mslam.priors.cache import ByteLRU
from mslam.priors.descriptors import patch_descriptors
from mslam.priors.twoview_flow import guided_flow, sift_keypoints

__all__ = ["FlowPrefetch", "pair_keys", "pair_work"]

#: ``(frame, partner) -> {cache key: value}``: the prefetched work of one pair, given the
#: cached values it may reuse (``dict`` keyed like the cache).
PairWork = Callable[[Frame, Frame | None, dict[Hashable, Any]], dict[Hashable, Any]]


class FlowPrefetch:
    """One prefetch in flight at a time (module docstring).

    Args:
        cache: the prior's cache, which receives the results.
        work: computes one pair's entries on the worker thread (it must not touch ``cache``).
        keys: ``(frame, partner) -> the cache keys work may produce``; the ones already
            cached are passed to ``work`` as its known values.
    """

    def __init__(
        self,
        cache: ByteLRU,
        work: PairWork,
        keys: Callable[[Frame, Frame | None], list[Hashable]],
    ) -> None:
        self.cache, self.work, self.keys = cache, work, keys
        self._index: int | None = None  # the frame being prefetched
        self._thread: threading.Thread | None = None
        self._out: dict[Hashable, Any] = {}

    def start(self, frame: Frame, partner: Frame | None) -> None:
        """Join the prefetch in flight, then start ``frame``'s (and its pair's) work."""
        self.join()
        known = {k: v for k in self.keys(frame, partner) if (v := self.cache.peek(k)) is not None}
        out: dict[Hashable, Any] = {}

        def run() -> None:
            with contextlib.suppress(Exception):  # dropped: recomputed (and raised) on demand
                out.update(self.work(frame, partner, known))

        self._index, self._out = int(frame.index), out
        self._thread = threading.Thread(target=run, name="twoview-prefetch", daemon=True)
        self._thread.start()

    def settle(self, *frames: Frame) -> None:
        """Join the prefetch when it is working on one of ``frames``."""
        if self._index is not None and any(int(f.index) == self._index for f in frames):
            self.join()

    def join(self) -> None:
        """Wait for the prefetch in flight, if any, and store its results in the cache."""
        thread, self._thread, self._index = self._thread, None, None
        if thread is None:
            return
        thread.join()
        for key, value in self._out.items():
            if key not in self.cache:
                self.cache.put(key, value)
        self._out = {}


def pair_keys(frame: Frame, partner: Frame | None) -> list[Hashable]:
    """The two-view prior's cache keys of ``frame``'s own work and of the pair (frame,
    partner): descriptors, both images' keypoints, the flow and the flow the other way."""
    h = hash(frame.rgb.tobytes())
    keys: list[Hashable] = [("desc", int(frame.index), h), ("sift", h)]
    if partner is not None:
        hp = hash(partner.rgb.tobytes())
        keys += [("sift", hp), ("flow", h, hp), ("flow", hp, h)]
    return keys


def pair_work(cfg: Any) -> PairWork:
    """The prefetch's work for a ``TwoViewPriorConfig``: what ``TwoViewPrior.pair(frame,
    partner)`` would compute from the two images alone, as ``{cache key: value}``; nothing
    already ``known``, and no flow when the other direction's is known (the prior swaps it)."""

    def work(frame: Frame, partner: Frame | None, known: dict[Hashable, Any]) -> dict:
        keys = pair_keys(frame, partner)
        out: dict[Hashable, Any] = {}
        if keys[0] not in known:
            out[keys[0]] = patch_descriptors(frame.rgb, cfg.desc)
        if partner is None or keys[3] in known or keys[4] in known:
            return out

        def keypoints(key: Hashable, f: Frame) -> Callable[[], Any]:
            def get() -> Any:  # on demand, as the prior's own: only when the guide is needed
                if key not in known and key not in out:
                    out[key] = sift_keypoints(f.rgb, cfg.guide)
                return known[key] if key in known else out[key]

            return get

        kp: list[Callable[[], Any] | None] = [None, None]
        if cfg.guide.enabled:
            kp = [keypoints(keys[1], frame), keypoints(keys[2], partner)]
        out[keys[3]] = guided_flow(frame.rgb, partner.rgb, kp[0], kp[1], cfg.fb_px, cfg.guide)
        return out

    return work
