"""The next frame's flow to its keyframe, computed while the current frame is tracked.

The frame loop (``mslam.system.run``) reads frame t + 1 before it processes frame t and hands
it to :meth:`mslam.priors.twoview.TwoViewPrior.prefetch` together with the frame it will
most likely be paired with: the last keyframe (``SlamSystem.pair_partner``). A worker
thread then computes what depends on those two images alone — the frame's patch
descriptors, both images' SIFT keypoints when the flow needs its guide, and the dense flow
both ways (:func:`mslam.priors.twoview_flow.guided_flow`) — while the main thread matches,
tracks and solves frame t. The pose of the pair is not prefetched: it depends on the depths
remembered from earlier pairs (the third view), which frame t may still change.

The worker never touches the prior's cache, and neither does the prefetch: the prior takes a
prefetched value (:meth:`FlowPrefetch.take`) at the moment it would have computed it, and
stores it then, as its own. The cache therefore sees the same entries in the same order as
without the prefetch, and evicts the same ones: that matters, because the prior reuses a
cached pair the other way round (its flows swapped, its pose inverted), which is not the
same number as computing that direction afresh. So the values are those computed on demand
and the trajectory is the same bit for bit (tests/app/test_twoview_prefetch.py). What is not
taken — frame t became a keyframe, and frame t + 1 is paired with it instead — is dropped
when frame t + 3's prefetch starts. A failed step is dropped too: it runs again, and raises,
when its result is asked for.

DIS and SIFT (OpenCV) release the GIL, so on two cores they overlap the main thread's
single-threaded Python (the pose refinement, the graph): benchmarks/RESULTS.md, "The next
frame's flow beside the current frame".

Public names: FlowPrefetch, desc_key, sift_key, flow_key, pair_keys, pair_work
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

__all__ = ["FlowPrefetch", "desc_key", "flow_key", "pair_keys", "pair_work", "sift_key"]

#: ``(frame, partner, known) -> {cache key: value}``: the prefetched work of one pair, given
#: the values already cached that it may reuse (keyed like the cache).
PairWork = Callable[[Frame, Frame | None, dict[Hashable, Any]], dict[Hashable, Any]]


class FlowPrefetch:
    """The prefetches of the next two frames (module docstring): the frame loop starts frame
    t + 1's before it processes frame t, so frame t's results, started one frame earlier, are
    kept until frame t + 2's prefetch starts. One worker runs at a time.

    Args:
        work: computes one pair's entries on the worker thread (it must not touch the cache).
        keys: ``(frame, partner) -> the cache keys work may produce``; the ones already
            cached are passed to ``work`` as its known values.
    """

    def __init__(self, work: PairWork, keys: Callable[[Frame, Frame | None], list[Hashable]]):
        self.work, self.keys = work, keys
        self._thread: threading.Thread | None = None
        #: (keys, results) of the earlier prefetch and of the latest one (the thread's).
        self._gens: list[tuple[set[Hashable], dict[Hashable, Any]]] = []

    def start(self, frame: Frame, partner: Frame | None, cache: ByteLRU) -> None:
        """Start ``frame``'s (and its pair's) work once the running one is done, dropping
        what the prefetch before that left untaken; ``cache`` is only looked at (``peek``),
        here, in the caller's thread."""
        self._wait()
        keys = self.keys(frame, partner)
        known = {k: v for k in keys if (v := cache.peek(k)) is not None}
        out: dict[Hashable, Any] = {}

        def run() -> None:
            with contextlib.suppress(Exception):  # dropped: recomputed (and raised) on demand
                out.update(self.work(frame, partner, known))

        self._gens = [*self._gens[-1:], (set(keys), out)]
        self._thread = threading.Thread(target=run, name="twoview-prefetch", daemon=True)
        self._thread.start()

    def take(self, key: Hashable, wait: bool = True) -> Any:
        """The prefetched value of ``key``, or None; a value is taken once. Waits for the
        worker when it may produce ``key``, unless ``wait`` is false (then None while it runs:
        a keyframe's keypoints, which the current frame may need before the worker is done)."""
        for n, (keys, out) in enumerate(self._gens):
            if key not in keys:
                continue
            if n == len(self._gens) - 1 and self._thread is not None:
                if not wait and self._thread.is_alive():
                    return None
                self._wait()
            if key in out:
                return out.pop(key)
        return None

    def join(self) -> None:
        """Wait for the prefetch in flight, if any, and drop what was not taken."""
        self._wait()
        self._gens = []

    def _wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
        self._thread = None


def desc_key(frame: Frame) -> tuple:
    """The two-view prior's cache key of ``frame``'s patch descriptors."""
    return ("desc", int(frame.index), hash(frame.rgb.tobytes()))


def sift_key(frame: Frame) -> tuple:
    """The cache key of ``frame``'s SIFT keypoints (by content: a repeated image shares them)."""
    return ("sift", hash(frame.rgb.tobytes()))


def flow_key(frame_i: Frame, frame_j: Frame) -> tuple:
    """The cache key of the flows of the pair (i, j) (by content); ``("flow", h_i, h_j)``."""
    return ("flow", hash(frame_i.rgb.tobytes()), hash(frame_j.rgb.tobytes()))


def pair_keys(frame: Frame, partner: Frame | None) -> list[Hashable]:
    """The two-view prior's cache keys of ``frame``'s own work and of the pair (frame,
    partner): descriptors, both images' keypoints, the flow and the flow the other way."""
    keys: list[Hashable] = [desc_key(frame), sift_key(frame)]
    if partner is not None:
        keys += [sift_key(partner), flow_key(frame, partner), flow_key(partner, frame)]
    return keys


def pair_work(cfg: Any) -> PairWork:
    """The prefetch's work for a ``TwoViewPriorConfig``: what ``TwoViewPrior.pair(frame,
    partner)`` would compute from the two images alone, as ``{cache key: value}``; nothing
    already ``known``, and no flow when the other direction's is known (the prior swaps it).
    The flow's value is ``((F_ij, F_ji, guided), guide_used)``: whether the flow asked for the
    keypoints, which the prior then looks up as its own flow would have."""

    def work(frame: Frame, partner: Frame | None, known: dict[Hashable, Any]) -> dict:
        out: dict[Hashable, Any] = {}
        if desc_key(frame) not in known:
            out[desc_key(frame)] = patch_descriptors(frame.rgb, cfg.desc)
        if partner is None:
            return out
        key = flow_key(frame, partner)
        if key in known or flow_key(partner, frame) in known:
            return out

        asked: list[Hashable] = []

        def keypoints(f: Frame) -> Callable[[], Any]:
            def get() -> Any:  # on demand, as the prior's own: only when the guide is needed
                k = sift_key(f)
                asked.append(k)
                if k not in known and k not in out:
                    out[k] = sift_keypoints(f.rgb, cfg.guide)
                return known[k] if k in known else out[k]

            return get

        kp: list[Callable[[], Any] | None] = [None, None]
        if cfg.guide.enabled:
            kp = [keypoints(frame), keypoints(partner)]
        flows = guided_flow(frame.rgb, partner.rgb, kp[0], kp[1], cfg.fb_px, cfg.guide)
        out[key] = (flows, bool(asked))
        return out

    return work
