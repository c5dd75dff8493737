"""The new-keyframe test's threshold relative to a keyframe's first tracked frame.

With ``tracking.keyframe_first_ratio`` r > 0 the tracker compares the overlap of each frame
with ``min(match_frac_thresh, r · overlap_first)``, ``overlap_first`` being the overlap of the
first frame tracked against that keyframe: a keyframe whose neighbour already sees little of it
(far depth failing the occlusion test, blurred or compressed images) is not replaced at once.
With r = 0 (upstream, ``base.yaml``) the threshold is ``match_frac_thresh``.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system.state import RunStats
from mslam.system.tracker import Tracker

N = 100


def _tracker(ratio: float) -> Tracker:
    cfg = load_config(None, [f"tracking.keyframe_first_ratio={ratio}"])
    return Tracker(cfg, load_kernels("ref"), None, RunStats(), threading.RLock())


def _threshold(tracker: Tracker, kf_index: int, distinct: int) -> float:
    """The threshold for a frame whose matches reach ``distinct`` of N frame pixels."""
    kf = SimpleNamespace(frame=SimpleNamespace(index=kf_index))
    idx = np.arange(N) % distinct
    ok = np.ones(N, bool)
    return tracker._keyframe_threshold(kf, idx, ok, ok, N)


def test_without_the_ratio_the_threshold_is_upstreams() -> None:
    tracker = _tracker(0.0)
    assert _threshold(tracker, 0, 20) == tracker.tracking_cfg.match_frac_thresh == 0.333


@pytest.mark.parametrize("first", [20, 30, 90])
def test_the_first_frame_sets_the_threshold_for_its_keyframe(first) -> None:
    tracker = _tracker(0.75)
    expected = min(0.333, 0.75 * first / N)
    assert _threshold(tracker, 7, first) == pytest.approx(expected)
    # Later frames of the same keyframe keep it, whatever they see.
    assert _threshold(tracker, 7, 5) == pytest.approx(expected)
    assert _threshold(tracker, 7, 100) == pytest.approx(expected)
    # A new keyframe measures again.
    assert _threshold(tracker, 12, 100) == pytest.approx(0.333)
