"""Recovery beyond relocalisation and the map-spread watch.

* A prior that goes blind for a stretch (no confident point, no usable descriptor): tracking
  and relocalisation fail on every frame of it, so the system starts a new map; the summary
  lists it (``maps``, a warning) and the frames after the stretch have poses again, in the new
  map, while the old map's keyframes keep the poses they had.
* A prior whose pointmaps grow 2 % per frame: tracking makes up for it with the keyframes'
  Sim(3) scales, which shrink, while the map's scale in world units (Sim(3) scale times the
  canonical points' distance) stays within the watch's factor; the spread watch reads the
  latter and stays silent, as on the same source without the growth (a world scale that runs
  away is flagged: ``test_map_spread_fires_on_a_steady_drift_or_runaway_spacing_only`` and
  tests/app/test_divergence_drift.py). The same prior claiming metric pointmaps (as one made
  from depth does) has the watch read the Sim(3) scales alone, and at 3 % per frame it fires,
  where the world scale stays under the factor.
"""

from __future__ import annotations

import numpy as np
import pytest
from blind_prior import BlindPrior

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.divergence import DivergenceConfig, map_spread
from mslam.system.outputs import evaluate_run, summary_dict
from mslam.system.recovery import Recovery, RecoveryConfig
from mslam.system.state import FrameStatus

LOOP = "synthetic:loop:48:64x48"
BLIND = range(12, 22)  # frames the blind prior sees nothing in
MAX_LOST = 4  # recovery.max_lost_frames in the blind run
GROWTH = 1.02  # the growing prior's scale factor per frame


class _GrowingPrior:
    """Wraps a prior; every pointmap of a pair or mono call on frame i is scaled by
    ``growth ** i`` (a prior whose scale runs away slowly, the same in both pointmaps), so its
    pointmaps are not in metres."""

    metric = False

    def __init__(self, prior, growth: float) -> None:
        self._p, self._g = prior, growth

    def __getattr__(self, name):
        return getattr(self._p, name)

    def mono(self, frame):
        X, C = self._p.mono(frame)
        return X * self._g**frame.index, C

    def pair(self, frame_i, frame_j):
        p = self._p.pair(frame_i, frame_j)
        k = self._g**frame_i.index
        return type(p)(p.X_ii * k, p.C_ii, p.D_ii, p.Q_ii,
                       p.X_ji * k, p.C_ji, p.D_ji, p.Q_ji)  # fmt: skip


class _MetricGrowingPrior(_GrowingPrior):
    """The growing prior claiming metric pointmaps (as one made from depth does)."""

    metric = True


class _KeyframePosesAtNewMap:
    """Observer: the keyframe poses at the frame where map 1 starts."""

    def __init__(self) -> None:
        self.snapshot: np.ndarray | None = None

    def after_frame(self, i, frame, system, status) -> None:
        if self.snapshot is None and len(system.recovery.maps) > 1:
            self.snapshot = system.keyframes.poses().copy()


def _run(wrap, overrides=(), observer=None):
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    cfg = load_config(None, overrides)
    src = open_source(LOOP, cfg)
    src.prior = wrap(src.prior)
    system, meta = run_slam(src, cfg, load_kernels("fast"), observer=observer)
    return system, summary_dict(system, meta, evaluate_run(system, src.sequence))


@pytest.fixture(scope="module")
def blind_run():
    obs = _KeyframePosesAtNewMap()
    system, s = _run(lambda p: BlindPrior(p, BLIND), [f"recovery.max_lost_frames={MAX_LOST}"], obs)
    return system, s, obs


def test_a_blind_stretch_starts_a_new_map_and_says_so(blind_run) -> None:
    _, s, _ = blind_run
    assert len(s["maps"]) >= 2, s["maps"]
    for new in s["maps"][1:]:
        # Started by the blind stretch, at most MAX_LOST frames after its end.
        assert BLIND[0] <= new["first_frame"] <= BLIND[-1] + MAX_LOST + 1
        assert "consecutive frames lost" in new["reason"]
        assert any(f"was started at frame {new['first_frame']}" in w for w in s["warnings"])
    assert not s["plausible"]
    assert sum(m["frames_posed"] for m in s["maps"]) == s["frames_with_pose"]


def test_frames_after_the_blind_stretch_are_posed_in_the_last_map(blind_run) -> None:
    system, s, _ = blind_run
    idx, _, T = system.frame_poses()
    assert np.all(np.isfinite(T))
    last = s["maps"][-1]
    later = np.arange(last["first_frame"] + 1, s["frames"])
    assert np.isin(later, idx).all(), "a frame after the last map's start has no pose"
    assert len(later) >= s["frames"] - 1 - BLIND[-1] - (MAX_LOST + 1)
    kf_of = {p.index: p.kf for p in system.poses if p.kf >= 0}
    assert all(kf_of[int(i)] >= last["first_keyframe"] for i in later)
    assert last["frames_posed"] == len(later) and last["keyframes"] > 1


def test_the_old_map_keeps_its_poses_and_the_new_one_starts_at_its_last_pose(blind_run) -> None:
    system, s, obs = blind_run
    first_new = s["maps"][1]["first_keyframe"]
    T_kf = system.keyframes.poses()
    np.testing.assert_array_equal(T_kf[:first_new], obs.snapshot[:first_new])
    # The new map's first keyframe took the final pose of map 0's last posed frame.
    idx, _, T = system.frame_poses()
    before = idx < s["maps"][1]["first_frame"]
    np.testing.assert_array_equal(system.keyframes[first_new].T_WC_init, T[before][-1])
    # No edge joins the maps.
    assert all((e.i < first_new) == (e.j < first_new) for e in system.graph.edges)


def test_recovery_counts_lost_frames_and_refusals() -> None:
    rec = Recovery(RecoveryConfig(max_lost_frames=3, max_refusals=2, refusal_window=10))
    lost, tracked = FrameStatus.LOST, FrameStatus.TRACKED
    assert rec.after_frame(0, lost, []) is None and rec.after_frame(1, lost, []) is None
    assert rec.after_frame(2, tracked, []) is None  # a posed frame restarts the count
    assert [rec.after_frame(i, lost, []) is None for i in (3, 4, 5)] == [True, True, False]
    rec.new_map(5, 7, "lost")
    assert rec.after_frame(6, tracked, [6]) is None
    assert rec.after_frame(20, tracked, [6, 20]) is None  # frame 6 left the window
    assert "2 implausible poses" in rec.after_frame(21, tracked, [6, 20, 21])
    assert [m["first_keyframe"] for m in rec.maps] == [0, 7] and rec.map_of(6) == 0


def _poses(scales: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    T = np.zeros((len(scales), 8))
    T[:, 0] = np.concatenate([[0.0], np.cumsum(spacing)])
    T[:, 6], T[:, 7] = 1.0, scales
    return T


def test_map_spread_fires_on_a_steady_drift_or_runaway_spacing_only() -> None:
    n = 20
    rng = np.random.default_rng(0)
    cfg = DivergenceConfig()
    steady = _poses(1.1 ** np.arange(n), np.full(n - 1, 0.1))
    assert "scale grew" in map_spread(steady, cfg)
    # The same total change, back and forth: no steady drift.
    wobble = _poses(np.exp(rng.normal(0.0, 0.3, n)), np.full(n - 1, 0.1))
    assert map_spread(wobble, cfg) is None
    runaway = _poses(np.ones(n), 0.1 * 1.5 ** np.arange(n - 1))
    assert "spacing" in map_spread(runaway, cfg)
    assert map_spread(steady[: cfg.spread_window], cfg) is None  # too few keyframes to judge


@pytest.mark.parametrize("growth", [1.0, GROWTH])
def test_the_spread_watch_reads_the_world_scale_not_the_prior_s(growth) -> None:
    system, s = _run(lambda p: _GrowingPrior(p, growth))
    assert [e for e in s["divergence_events"] if e["kind"] == "spread"] == []
    assert not any("the map runs away" in w for w in s["warnings"])
    T = system.keyframes.poses()
    depth = [np.median(np.linalg.norm(np.reshape(kf.state.X_canon, (-1, 3)), axis=1))
             for kf in system.keyframes]  # fmt: skip
    w, cfg = DivergenceConfig().spread_window, DivergenceConfig()
    log_world = np.log(T[:, 7] * np.asarray(depth))
    world = np.exp(np.abs(log_world[w:] - log_world[:-w]))
    assert world.max() < cfg.max_scale_drift  # the map's scale in world units holds
    if growth != 1.0:  # while the Sim(3) scales make up for the prior's growth
        assert T[-1, 7] < 0.8 * T[0, 7]


def test_for_a_metric_prior_the_spread_watch_reads_the_sim3_scales() -> None:
    # In metres a keyframe's points measure the scene, so only the Sim(3) scales can drift:
    # the same 3 % growth per frame that the world scale leaves under the watch's factor
    # (module docstring) is a scale drift when the prior claims metres.
    _, s = _run(lambda p: _MetricGrowingPrior(p, 1.03))
    spread = [e for e in s["divergence_events"] if e["kind"] == "spread"]
    assert spread and "scale shrank" in spread[0]["reason"]
    assert any("the map runs away" in w for w in s["warnings"])
