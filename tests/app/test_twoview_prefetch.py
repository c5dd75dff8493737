"""The two-view prior's prefetch (``twoview_prior.prefetch``, on by default): the next frame's
flow to its keyframe, computed on a worker thread while the current frame is tracked, gives
the trajectory of a run without it bit for bit, is really used (flows computed on the worker
thread), and leaves no thread behind, after a run or after an exception.

Short RGB-only runs on a synthetic forward motion (96x72, 20 frames, fast kernels in float64), one run
per setting.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from mslam.config import load_config
from mslam.datasets.frame import Frame
from mslam.kernels import load_kernels
from mslam.priors import twoview_prefetch
from mslam.priors.cache import ByteLRU
from mslam.system import open_source, run_slam

SOURCE = "synthetic:forward:20:96x72"
_FLOW = twoview_prefetch.guided_flow  # the flow itself, whatever a test patches


def _workers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "twoview-prefetch"]


def _run(prefetch: bool, monkeypatch: pytest.MonkeyPatch):
    """(system, the names of the threads that computed each flow) of one run."""
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    threads: list[str] = []

    def counted(*args, **kwargs):
        threads.append(threading.current_thread().name)
        return _FLOW(*args, **kwargs)

    for module in ("twoview", "twoview_prefetch"):  # on demand, and the prefetch's
        monkeypatch.setattr(f"mslam.priors.{module}.guided_flow", counted)
    cfg = load_config("twoview", [f"twoview_prior.prefetch={str(prefetch).lower()}"])
    src = open_source(SOURCE, cfg, prior="twoview")
    assert src.prior.prefetching == prefetch
    system, _ = run_slam(src, cfg, load_kernels("fast"))
    return system, threads


def test_prefetch_gives_the_same_trajectory_and_no_thread_is_left(monkeypatch) -> None:
    before = _workers()
    on, threads_on = _run(True, monkeypatch)
    off, threads_off = _run(False, monkeypatch)
    assert _workers() == before == []
    ia, _, Ta = on.frame_poses()
    ib, _, Tb = off.frame_poses()
    assert len(ia) >= 15 and len(on.keyframes) >= 2
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_array_equal(Ta, Tb)
    for ka, kb in zip(on.keyframes, off.keyframes, strict=True):
        np.testing.assert_array_equal(ka.state.X_canon, kb.state.X_canon)
    # Without prefetch every flow is computed on the main thread; with it, most tracking
    # pairs' flows come from the worker, and a prefetched flow is wasted only when the frame
    # before became a keyframe (the frame is then paired with that one).
    assert "twoview-prefetch" not in threads_off
    assert threads_on.count("twoview-prefetch") >= len(ia) // 2
    assert len(threads_on) <= len(threads_off) + len(on.keyframes)


def test_no_prefetch_thread_is_left_after_an_exception(monkeypatch) -> None:
    from mslam.system.tracker import Tracker

    track = Tracker.track
    calls = []

    def failing(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 4:
            raise RuntimeError("tracking failed")
        return track(self, *args, **kwargs)

    monkeypatch.setattr(Tracker, "track", failing)
    cfg = load_config("twoview", [])
    src = open_source(SOURCE, cfg, prior="twoview")
    assert src.prior.prefetching
    with pytest.raises(RuntimeError, match="tracking failed"):
        run_slam(src, cfg, load_kernels("fast"))
    assert _workers() == []


def _frame(index: int, seed: int) -> Frame:
    rgb = np.random.default_rng(seed).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    return Frame(index=index, timestamp=float(index), rgb=rgb)


def test_a_value_is_taken_once_the_cache_is_not_touched_and_a_failure_is_dropped() -> None:
    cache = ByteLRU(2**20)
    cache.put(("y", 1), np.zeros(2))
    seen: list[dict] = []

    def work(frame, partner, known):
        seen.append(known)
        if frame.index == 2:
            raise ValueError("failed step")
        return {("x", frame.index): np.full(3, frame.index)}

    keys = lambda frame, partner: [("x", frame.index), ("y", frame.index)]
    pre = twoview_prefetch.FlowPrefetch(work, keys)
    f0, f1, f2 = _frame(0, 0), _frame(1, 1), _frame(2, 2)
    pre.start(f1, f0, cache)
    assert pre.take(("x", 0)) is None  # not a key of this prefetch: no wait, nothing
    np.testing.assert_array_equal(pre.take(("x", 1)), [1, 1, 1])
    assert pre.take(("x", 1)) is None  # taken once
    assert list(seen[0]) == [("y", 1)]  # what was cached was handed to the work
    assert cache.keys() == [("y", 1)]  # the prefetch stores nothing itself
    pre.start(f2, None, cache)  # its work raises: nothing to take
    assert pre.take(("x", 2)) is None
    pre.start(f1, f0, cache)
    pre.join()  # what was not taken is dropped
    assert pre.take(("x", 1)) is None
    assert _workers() == []


def test_a_small_cache_keeps_the_trajectory(monkeypatch) -> None:
    """With a cache that evicts every few frames, the prefetch still gives the same run: the
    prior takes a prefetched value when it would have computed it, so the cache keeps and
    evicts the same entries (a pair cached the other way round is reused swapped, which is
    not the same number as computing that direction)."""
    small = 3 * 2**20  # about 4 frames' descriptors at 96x72

    def run(prefetch: bool):
        cfg = load_config("twoview", [f"twoview_prior.prefetch={str(prefetch).lower()}"])
        src = open_source(SOURCE, cfg, prior="twoview")
        src.prior.cache = ByteLRU(small)
        system, _ = run_slam(src, cfg, load_kernels("fast"))
        assert src.prior.cache.bytes <= small
        return system.frame_poses()

    on, off = run(True), run(False)
    np.testing.assert_array_equal(on[0], off[0])
    np.testing.assert_array_equal(on[2], off[2])
