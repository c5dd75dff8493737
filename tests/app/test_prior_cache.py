"""The priors' per-frame caches: one :class:`ByteLRU` bounded in bytes (configurable).

Every prior (synthetic, RGB-D, two-view, MASt3R with a stand-in network) keeps its per-frame
work in ``prior.cache``: it stays within ``cache_bytes``, a hit gives the same arrays as
computing afresh (a prior that keeps nothing), and an evicted entry is recomputed to the same
value.
"""

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


def test_put_peek_pop_clear():
    cache = ByteLRU(max_bytes=2 * 800)
    cache.put("a", np.zeros(100))
    cache.put("b", np.zeros(100))
    assert cache.peek("a") is not None and cache.peek("z", 7) == 7
    cache.put("c", np.zeros(100))  # peek did not refresh "a": it is evicted
    assert list(cache.keys()) == ["b", "c"] and cache.bytes == 1600
    cache.put("b", np.zeros(50))  # replaced, now the most recent
    assert list(cache.keys()) == ["c", "b"] and cache.bytes == 1200
    assert cache.pop("c").shape == (100,) and cache.pop("c") is None and cache.bytes == 400
    cache.clear()
    assert len(cache) == 0 and cache.bytes == 0


def test_nbytes_counts_objects_that_report_nbytes():
    class Tensor:  # torch tensors report nbytes like NumPy arrays
        nbytes = 40

    assert nbytes((Tensor(), [np.zeros(2)], {"k": None, "s": "text", "n": 3})) == 56


# -- every prior ----------------------------------------------------------------------------

W, H = 96, 72


@pytest.fixture(scope="module")
def seq():
    from mslam.datasets.synthetic import make_sequence

    return make_sequence("loop", n_frames=40, width=W, height=H, seed=0)


def _desc(cache_bytes):
    from mslam.priors.descriptors import DescriptorConfig

    return dataclasses.replace(DescriptorConfig(), cache_bytes=cache_bytes)


def _synthetic(seq, cache_bytes):
    from mslam.priors.synthetic import SyntheticPrior, SyntheticPriorConfig

    return SyntheticPrior(seq, SyntheticPriorConfig(desc=_desc(cache_bytes)))


def _rgbd(seq, cache_bytes):
    from mslam.priors.rgbd import RGBDPrior, RGBDPriorConfig

    return RGBDPrior(seq, RGBDPriorConfig(n_features=500, desc=_desc(cache_bytes)))


def _twoview(seq, cache_bytes):
    from mslam.priors.twoview import TwoViewPrior, TwoViewPriorConfig

    return TwoViewPrior(cfg=TwoViewPriorConfig(desc=_desc(cache_bytes)))


def _mast3r(seq, cache_bytes):
    from stand_ins import StandInMast3r

    from mslam.priors.mast3r import Mast3rConfig, Mast3rPrior, NumpyBackend

    cfg = Mast3rConfig(size=224, apply_activations=True, cache_bytes=cache_bytes)
    return Mast3rPrior(StandInMast3r(), cfg, backend=NumpyBackend())


PRIORS = {"synthetic": _synthetic, "rgbd": _rgbd, "twoview": _twoview, "mast3r": _mast3r}


def _same(a, b) -> bool:
    return all(
        np.array_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
    )


def _caches(prior):
    return [c for c in (prior.cache, getattr(prior, "views", None)) if c is not None]


@pytest.mark.parametrize("name", sorted(PRIORS))
def test_prior_cache_hits_match_fresh_computation(seq, name):
    prior = PRIORS[name](seq, DEFAULT_CACHE_BYTES)
    first = prior.pair(seq[2], seq[0])
    assert len(prior.cache) > 0 and prior.cache.bytes > 0
    stored = []
    prior.cache.put = lambda key, value: stored.append(key)  # no miss may store anything
    again = prior.pair(seq[2], seq[0])
    assert stored == [] and _same(first, again)
    fresh = PRIORS[name](seq, 0).pair(seq[2], seq[0])  # keeps nothing: computes everything
    assert _same(first, fresh)


@pytest.mark.parametrize("name", sorted(PRIORS))
def test_prior_cache_stays_within_its_bytes_and_evicts(seq, name):
    probe = PRIORS[name](seq, DEFAULT_CACHE_BYTES)
    first = probe.pair(seq[1], seq[0])
    bound = probe.cache.bytes  # what one pair's two frames take
    prior = PRIORS[name](seq, bound)
    assert _same(prior.pair(seq[1], seq[0]), first)
    keys = set(prior.cache.keys())
    for i in range(2, 6):
        prior.pair(seq[i], seq[i - 1])
        for cache in _caches(prior):
            assert 0 < cache.bytes <= bound
            assert cache.bytes == sum(nbytes(cache.peek(k)) for k in cache.keys())
    assert not keys & set(prior.cache.keys())  # the first pair's entries were evicted
    assert _same(prior.pair(seq[1], seq[0]), first)  # ... and recomputed to the same values
