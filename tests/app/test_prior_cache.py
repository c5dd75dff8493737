"""Issue 13 §9: the priors' per-frame caches are bounded in bytes (configurable)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mslam.priors.cache import DEFAULT_CACHE_BYTES, ByteLRU, nbytes


def test_byte_lru_evicts_least_recently_used():
    cache = ByteLRU(max_bytes=3 * 800)
    calls = []

    def make(k):
        calls.append(k)
        return (np.zeros(100), {"x": np.zeros(0)})  # 800 bytes

    for k in (0, 1, 2, 0, 3):  # 0 is refreshed, so 1 is evicted by 3
        cache.get(k, lambda k=k: make(k))
    assert cache.bytes == 3 * 800 and len(cache) == 3
    cache.get(0, lambda: make(0))
    cache.get(1, lambda: make(1))
    assert calls == [0, 1, 2, 3, 1]
    assert nbytes([np.zeros(2), (np.zeros(3, np.float32),)]) == 28


def test_entry_larger_than_the_bound_is_not_kept():
    cache = ByteLRU(max_bytes=10)
    assert cache.get("big", lambda: np.zeros(100)).shape == (100,)
    assert len(cache) == 0 and cache.bytes == 0
    with pytest.raises(ValueError, match="max_bytes"):
        ByteLRU(-1)


def test_compute_alongside_stores_missing_entries_and_reraises():
    import threading

    cache = ByteLRU(max_bytes=10_000)
    cache.get("a", lambda: np.zeros(1))
    threads = []
    b_may_finish = threading.Event()

    def job(v, wait=None):
        threads.append(threading.current_thread().name)
        if wait is not None:
            assert wait.wait(5.0)
        return np.full(2, v)

    join = cache.compute_alongside(
        {"a": lambda: job(9.0), "c": lambda: job(1.0), "b": lambda: job(2.0, b_may_finish)}
    )
    join("c")  # the first job only: returns while "b" still waits
    assert "c" in cache and "b" not in cache
    b_may_finish.set()
    join()
    assert threads == ["cache-alongside"] * 2  # only the missing entries, on the worker
    assert cache.get("a", lambda: None)[0] == 0.0 and cache.get("b", lambda: None)[0] == 2.0
    cache.compute_alongside({"a": lambda: job(5.0)})()  # nothing to do
    assert len(threads) == 2

    def fail():
        raise RuntimeError("no keypoints")

    join = cache.compute_alongside({"d": fail, "e": lambda: job(3.0)})
    with pytest.raises(RuntimeError, match="no keypoints"):
        join()
    assert "d" not in cache and "e" not in cache and len(threads) == 2  # nothing after a failure


def test_synthetic_prior_cache_stays_within_its_bytes():
    from mslam.datasets.synthetic import make_sequence
    from mslam.priors.descriptors import DescriptorConfig
    from mslam.priors.synthetic import SyntheticPrior, SyntheticPriorConfig

    seq = make_sequence("loop", n_frames=8, width=32, height=24)
    per_frame = 32 * 24 * (24 * 4 + 8)  # float32 descriptors and float64 contrast
    cfg = SyntheticPriorConfig(
        desc=dataclasses.replace(DescriptorConfig(), cache_bytes=3 * per_frame)
    )
    prior = SyntheticPrior(seq, cfg)
    for i in range(1, 8):
        prior.pair(seq[i - 1], seq[i])
    assert 0 < prior._desc_cache.bytes <= 3 * per_frame and len(prior._desc_cache) <= 3
    assert DEFAULT_CACHE_BYTES <= 256 * 2**20
