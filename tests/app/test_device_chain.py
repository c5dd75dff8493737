"""The frame's device chain in the SLAM loop: the tracker's resident matching and fusion
(``mslam_fast.resident``) give the NumPy entries' trajectory bit for bit and upload a
keyframe's arrays once per keyframe, not per frame; the RGB-D prior's prefetch
(``rgbd_prior.prefetch``) gives the same trajectory and leaves no thread behind, after a
run or after an exception.

Short RGB-D runs on a synthetic sequence (96x72, 16 frames; weighted fusion, so the fusion
kernel runs), cached per setting within the module.
"""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam

SOURCE = "synthetic:forward:16:96x72"
#: rgbd.yaml with weighted fusion, so that the fusion kernel runs.
CONFIG = ("rgbd", ["tracking.filtering_mode=weighted_pointmap"])
_RUNS: dict = {}


def _workers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "cache-alongside"]


def _run(resident: bool = True, prefetch: bool = False):
    """(system, uploads) of one cached run with the fast kernels in float64."""
    key = (resident, prefetch)
    if key not in _RUNS:
        import mslam_fast
        from mslam_fast import resident as res

        mslam_fast.init("cpu", "f64")
        cfg = load_config(CONFIG[0], [*CONFIG[1], f"rgbd_prior.prefetch={str(prefetch).lower()}"])
        src = open_source(SOURCE, cfg, prior="rgbd")
        kernels = load_kernels("fast")
        if not resident:
            kernels = replace(kernels, resident=None)
        res.reset_uploads()
        system, _ = run_slam(src, cfg, kernels)
        _RUNS[key] = (system, res.uploads())
    return _RUNS[key]


def _same_run(a, b) -> None:
    ia, _, Ta = a.frame_poses()
    ib, _, Tb = b.frame_poses()
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_array_equal(Ta, Tb)
    assert len(a.keyframes) == len(b.keyframes)
    for ka, kb in zip(a.keyframes, b.keyframes, strict=True):
        np.testing.assert_array_equal(ka.state.X_canon, kb.state.X_canon)
        np.testing.assert_array_equal(ka.state.C, kb.state.C)


def test_resident_chain_gives_the_numpy_trajectory() -> None:
    system, _ = _run(resident=True)
    reference, n = _run(resident=False)
    assert system.stats.lost_frames == 0 and len(system.keyframes) >= 2
    _same_run(system, reference)
    assert "matching.D21" not in n  # the NumPy entries do not upload anything


def test_keyframe_arrays_are_uploaded_once_per_keyframe() -> None:
    system, n = _run(resident=True)
    tracked = n["matching.X11"]  # one upload of the frame's points per tracked frame
    assert tracked >= len(system.keyframes) + 5
    # The keyframe's descriptors: once for each keyframe tracked against, not once per frame.
    assert 1 <= n["matching.D21"] <= len(system.keyframes)
    # The fused pointmap: once per keyframe (the tracker's fusion keeps it on the device).
    assert n["fusion.X"] == tracked and 1 <= n["fusion.X_canon"] <= len(system.keyframes)
    assert n["tracking.X_f"] == tracked  # the solve's inputs once per frame, not per iteration


def test_prefetch_gives_the_same_trajectory_and_no_thread_is_left() -> None:
    before = _workers()
    system, _ = _run(prefetch=True)
    assert _workers() == before == []
    _same_run(system, _run(prefetch=False)[0])


def test_no_prefetch_thread_is_left_after_an_exception(monkeypatch: pytest.MonkeyPatch) -> None:
    from mslam.system.tracker import Tracker

    track = Tracker.track
    calls = []

    def failing(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("tracking failed")
        return track(self, *args, **kwargs)

    monkeypatch.setattr(Tracker, "track", failing)
    cfg = load_config(CONFIG[0], [*CONFIG[1], "rgbd_prior.prefetch=true"])
    src = open_source(SOURCE, cfg, prior="rgbd")
    assert src.prior.prefetching
    with pytest.raises(RuntimeError, match="tracking failed"):
        run_slam(src, cfg, load_kernels("fast"))
    assert _workers() == []


class _Unreadable:
    """The frames of ``seq`` with frame ``bad`` unreadable (``OSError``)."""

    def __init__(self, seq, bad: int) -> None:
        self.seq, self.bad = seq, bad

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int):
        if i == self.bad:
            raise OSError(f"frame {i}: cannot read")
        return self.seq[i]


@pytest.mark.parametrize("skip", [True, False])
def test_a_frame_read_ahead_fails_in_its_own_turn(skip: bool) -> None:
    def run(prefetch: bool):
        cfg = load_config(CONFIG[0], [*CONFIG[1], f"rgbd_prior.prefetch={str(prefetch).lower()}"])
        src = open_source(SOURCE, cfg, prior="rgbd", max_frames=8)
        src = replace(src, sequence=_Unreadable(src.sequence, 5))
        with pytest.warns(RuntimeWarning, match="skipping frame 5"):
            return run_slam(src, cfg, load_kernels("fast"), skip_bad_frames=True)[0]

    if skip:
        on, off = run(True), run(False)
        assert on.stats.skipped_frames == off.stats.skipped_frames == 1
        assert on.stats.frames == off.stats.frames == 7  # the frames after it are processed
        _same_run(on, off)
    else:
        cfg = load_config(CONFIG[0], [*CONFIG[1], "rgbd_prior.prefetch=true"])
        src = open_source(SOURCE, cfg, prior="rgbd", max_frames=8)
        src = replace(src, sequence=_Unreadable(src.sequence, 5))
        with pytest.raises(ValueError, match="cannot read frame 5"):
            run_slam(src, cfg, load_kernels("fast"))
        assert _workers() == []
