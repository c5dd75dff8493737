"""The spread watch on keyframe scales that drift unevenly (``map_spread``,
``DivergenceConfig.max_uneven_drift``), and how severe a drift is (``DivergenceMonitor.severity``,
``DivergenceConfig.max_confounded_drift``).

A monocular map whose Sim(3) scale shrinks by a large factor in uneven steps (sensor noise at
the working resolution: some keyframes shrink a lot, some recover a little) is a drift even
though the steadiness test does not fire; a camera walking towards a wall, whose normalised
prior's scale shrinks just as much but in step with the distance walked, is not.
"""

from __future__ import annotations

import numpy as np
import pytest

from mslam.system.divergence import (
    DivergenceConfig,
    DivergenceMonitor,
    divergence_report,
    map_spread,
)

CFG = DivergenceConfig()
N_KF = CFG.spread_window + 3  # keyframes: more than one window
#: Log scale change per keyframe step, alternating: big shrinks, small recoveries (net a
#: factor 37 over a window, 43 % of the total change net).
UNEVEN_STEPS = (-1.5, 0.6)
#: Distance of the wall from the first keyframe and from the last (metres).
WALL_FROM, WALL_TO = 60.0, 0.5


def _poses(centres: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(K, 8) poses looking along the world's +z axis (identity rotation)."""
    T = np.zeros((len(scales), 8))
    T[:, :3] = centres
    T[:, 6], T[:, 7] = 1.0, scales
    return T


def _window_stats(T: np.ndarray) -> tuple[float, float]:
    """Net factor and net share of the total log change over the watch's window."""
    d = np.diff(np.log(T[-CFG.spread_window - 1 :, 7]))
    return float(np.exp(abs(d.sum()))), abs(float(d.sum())) / float(np.abs(d).sum())


def _uneven(scale_of_drift: float) -> np.ndarray:
    """A camera moving sideways (never towards the scene) whose scale alternates big shrinks
    and small recoveries, ``UNEVEN_STEPS`` scaled by ``scale_of_drift``."""
    steps = scale_of_drift * np.resize(np.array(UNEVEN_STEPS), N_KF - 1)
    log_s = np.concatenate([[0.0], np.cumsum(steps)])
    centres = np.outer(np.arange(N_KF), [0.1, 0.0, 0.0])
    return _poses(centres, np.exp(log_s))


def test_an_uneven_drift_beyond_the_uneven_factor_is_flagged() -> None:
    T = _uneven(1.0)
    factor, share = _window_stats(T)
    assert share < CFG.min_drift_trend  # the steadiness test alone would pass it
    assert factor > CFG.max_uneven_drift
    why = map_spread(T, CFG, np.ones(N_KF))
    assert why is not None and "scale shrank" in why and "unevenly" in why
    assert "scale grew" in map_spread(T[::-1], CFG, np.ones(N_KF))  # the other way too
    # The rule is the factor: a config that tolerates it stays silent on the same map.
    lenient = DivergenceConfig(max_uneven_drift=2 * factor)
    assert map_spread(T, lenient, np.ones(N_KF)) is None


def test_an_uneven_wobble_below_the_uneven_factor_is_not_flagged() -> None:
    T = _uneven(0.5)
    factor, share = _window_stats(T)
    assert CFG.max_scale_drift < factor < CFG.max_uneven_drift
    assert share < CFG.min_drift_trend
    assert map_spread(T, CFG, np.ones(N_KF)) is None


def test_a_steady_walk_towards_a_wall_with_matching_depths_is_not_flagged() -> None:
    dist = np.geomspace(WALL_FROM, WALL_TO, N_KF)  # the scene's distance at each keyframe
    centres = np.outer(WALL_FROM - dist, [0.0, 0.0, 1.0])  # walking along the optical axis
    normalised = _poses(centres, dist)  # a prior that normalises its pointmaps to distance 1
    factor, share = _window_stats(normalised)
    assert factor > CFG.max_uneven_drift and share >= CFG.min_drift_trend
    assert map_spread(normalised, CFG, np.ones(N_KF)) is None
    assert map_spread(normalised[::-1], CFG, np.ones(N_KF)[::-1]) is None  # walking away
    metric = _poses(centres, np.ones(N_KF))  # a metric prior: the depths carry the distance
    assert map_spread(metric, CFG, dist) is None
    # Without the depths, or with a camera that does not approach the scene, it is a drift.
    assert "scale shrank" in map_spread(normalised, CFG)
    sideways = _poses(np.outer(WALL_FROM - dist, [1.0, 0.0, 0.0]), dist)
    assert "scale shrank" in map_spread(sideways, CFG, np.ones(N_KF))


def test_a_pointmap_scale_change_that_leaves_the_scene_distance_is_not_flagged() -> None:
    # Keyframes at rest whose canonical points come at another scale each time (mono or fused
    # pointmaps): the Sim(3) scale grows five-fold while s_k · depth_k, the scene's distance in
    # world units, stays put.
    scales = np.geomspace(1.0, 5.0, N_KF)
    T = _poses(np.zeros((N_KF, 3)), scales)
    factor, share = _window_stats(T)
    assert factor > CFG.max_scale_drift and share >= CFG.min_drift_trend
    assert map_spread(T, CFG, 1.0 / scales) is None
    # The same scales over pointmaps of one scale move the scene: a drift.
    assert "scale grew" in map_spread(T, CFG, np.ones(N_KF))


def _sideways_drift(factor: float) -> np.ndarray:
    """Keyframes moving sideways (never towards the scene) whose scale shrinks steadily by
    ``factor`` over the watch's window."""
    log_s = np.linspace(0.0, -np.log(factor) * (N_KF - 1) / CFG.spread_window, N_KF)
    return _poses(np.outer(np.arange(N_KF), [0.1, 0.0, 0.0]), np.exp(log_s))


def test_a_normalised_prior_s_drift_is_a_caution_up_to_the_confounded_factor() -> None:
    # The world scale read with the points' distances also moves with the scene's distance:
    # a factor between the watch's and the confounded factor is reported, not warned about.
    factor = np.sqrt(CFG.max_scale_drift * CFG.max_confounded_drift)
    T = _sideways_drift(factor)
    assert _window_stats(T)[0] == pytest.approx(factor)
    mon = DivergenceMonitor()
    assert not mon.check_map(40, T, np.ones(N_KF))
    assert mon.warnings() == []
    assert len(mon.cautions()) == 1 and "at frame 40" in mon.cautions()[0]
    (event,) = mon.events
    assert event["severity"] == "caution" and event["factor"] == pytest.approx(factor)
    report = divergence_report(mon, [], T, [])
    assert report["plausible"] and report["cautions"] == mon.cautions()
    # Seen again in the same map: no second event, the largest factor kept; in a new map:
    # reported again.
    mon.check_map(41, _sideways_drift(1.5 * factor), np.ones(N_KF))
    assert len(mon.events) == 1
    assert event["factor"] == pytest.approx(factor)
    assert event["largest_factor"] == pytest.approx(1.5 * factor)
    mon.new_map()
    mon.check_map(42, T, np.ones(N_KF))
    assert len(mon.events) == 2


def test_a_drift_beyond_the_confounded_factor_or_of_a_metric_prior_is_a_runaway() -> None:
    beyond = _sideways_drift(2 * CFG.max_confounded_drift)
    mon = DivergenceMonitor()
    mon.check_map(40, _sideways_drift(np.sqrt(CFG.max_confounded_drift)), np.ones(N_KF))
    mon.check_map(50, beyond, np.ones(N_KF))  # after a caution, the runaway is still reported
    assert [e["severity"] for e in mon.events] == ["caution", "runaway"]
    assert len(mon.warnings()) == 1 and "the map runs away (at frame 50)" in mon.warnings()[0]
    assert not divergence_report(mon, [], beyond, [])["plausible"]
    # A metric prior's Sim(3) scales have no scene distance in them: any drift is a runaway.
    metric = DivergenceMonitor()
    metric.check_map(40, _sideways_drift(np.sqrt(CFG.max_confounded_drift)), None)
    assert [e["severity"] for e in metric.events] == ["runaway"] and metric.cautions() == []
