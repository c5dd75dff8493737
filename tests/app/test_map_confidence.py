"""Map points: confidence of the two-view prior, filled points kept out of fusion and export."""

from __future__ import annotations

import numpy as np
import pytest

from mslam.datasets.synthetic import make_sequence
from mslam.priors.base import NO_INFO_C
from mslam.priors.twoview import TwoViewPrior
from mslam.system.outputs import C_CONF_THRESHOLD
from mslam.system.tracker import without_filler
from mslam_ref import fusion

W, H = 128, 96


@pytest.fixture(scope="module")
def seq():
    # The forward path at 128x96: pixels near the border leave the next image (filled).
    return make_sequence("forward", n_frames=40, width=W, height=H, seed=0)


@pytest.mark.parametrize("calibrated", [True, False])
def test_confidence_orders_the_depth_error(seq, calibrated):
    """Exported points (C > threshold) have a smaller depth error than the points under the
    threshold, and those a smaller one than the filled points, which have the lowest C."""
    prior = TwoViewPrior(seq.K, (W, H)) if calibrated else TwoViewPrior()
    p = prior.pair(seq[0], seq[4])
    assert prior.last_status == "ok"
    C, z_est, z = p.C_ii, p.X_ii[..., 2], seq[0].depth
    filled = C == NO_INFO_C
    above = C > C_CONF_THRESHOLD
    below = ~above & ~filled
    assert np.all(C >= NO_INFO_C) and filled.any() and below.any() and above.mean() > 0.5
    # Filled points copy the depth of a triangulated pixel (nearest fill): no new depth.
    assert np.all(np.isin(z_est[filled], z_est[~filled]))
    rel = np.abs(np.median(z / z_est) * z_est - z) / z
    assert np.median(rel[above]) < np.median(rel[below]) < np.median(rel[filled])


def _state(X, C):
    return fusion.init_pointmap(np.asarray(X, float), np.asarray(C, float))


def test_a_filled_point_does_not_move_the_fused_point():
    state = _state([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], [5.0, 5.0])
    X_new = np.array([[0.0, 0.0, 9.0], [0.0, 0.0, 4.0]])
    C_new = np.array([NO_INFO_C, 5.0])
    s, X = without_filler(state, X_new, C_new)
    out = fusion.update_pointmap(s, X, C_new)
    assert out.X_canon[0, 2] == 2.0  # the filled 9 m is not averaged in
    assert out.X_canon[1, 2] == 3.5  # a measured point is
    assert np.all(state.X_canon == [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])  # input untouched


def test_a_measured_point_replaces_filler_and_filler_alone_stays_unexported():
    state = _state([[0.0, 0.0, 7.0], [0.0, 0.0, 7.0]], [NO_INFO_C, NO_INFO_C])
    X_new = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 8.0]])
    C_new = np.array([6.0, NO_INFO_C])
    s, X = without_filler(state, X_new, C_new)
    out = fusion.update_pointmap(s, X, C_new)
    assert out.X_canon[0, 2] == 2.0  # the measurement, not a mix with the filled 7 m
    C_avg = fusion.average_confidence(out)
    assert C_avg[0] > C_CONF_THRESHOLD  # exported
    assert C_avg[1] == NO_INFO_C  # never measured: below any export threshold >= 1


def test_tracking_fuses_upstreams_average_and_the_map_fuses_without_filler():
    """``Keyframe.state`` stays paper Eq. 8 (filled points included, as upstream); the map's
    ``Keyframe.X_map`` is the same average without them, with the same ``C`` and ``N``."""
    import threading

    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.priors.base import PairPrediction
    from mslam.system.keyframes import Keyframe
    from mslam.system.state import RunStats
    from mslam.system.tracker import Tracker
    from mslam_ref import sim3

    h, w = 1, 2
    X0 = np.array([[[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]]])
    kf = Keyframe(
        frame=None, T_WC=sim3.identity(), state=_state(X0.reshape(-1, 3), [5.0, 5.0]), shape=(h, w)
    )
    X_new = np.array([[[0.0, 0.0, 8.0], [0.0, 0.0, 4.0]]])
    C_new = np.array([[NO_INFO_C, 5.0]])
    D, Q = np.ones((h, w, 1)), np.ones((h, w))
    p = PairPrediction(X_new, C_new, D, Q, X_new, C_new, D, Q)
    tracker = Tracker(load_config("base"), load_kernels("ref"), None, RunStats(), threading.RLock())
    tracker._fuse(kf, p, sim3.identity())
    assert kf.state.X_canon[0, 2] == 3.0  # (5 * 2 + 1 * 8) / 6: the filled 8 m pulls
    assert kf.X_map[0, 2] == 2.0  # the map ignores it
    assert kf.X_map[1, 2] == kf.state.X_canon[1, 2] == 3.5
    assert kf.state.N == 2 and np.all(kf.state.C == [6.0, 10.0])


def test_a_keyframe_at_the_wrong_scale_is_found_and_rescaled(seq):
    """Four keyframes with exact depth; one's pointmap 1.4x too large: its log-range ratio
    against the others is log 1.4, theirs ~0, and only it is rescaled (by 1 / 1.4)."""
    from tolerances import SCALE_CONSENSUS

    from mslam.system.map_scale import keyframe_scale_disagreement, scale_corrections
    from mslam_ref.pointmap import backproject

    frames = [seq[i] for i in (0, 2, 4, 6)]
    X = np.stack([backproject(f.depth, seq.K) for f in frames])
    X[2] *= 1.4
    C = np.full(X.shape[:3], 5.0)
    T_WC = np.stack([f.T_WC for f in frames])
    m = keyframe_scale_disagreement(X, C, T_WC, C_CONF_THRESHOLD)
    assert abs(m[2] - np.log(1.4)) < SCALE_CONSENSUS
    assert np.all(np.abs(np.delete(m, 2)) < SCALE_CONSENSUS)
    f = scale_corrections(X, C, T_WC, C_CONF_THRESHOLD, tolerance=0.2)
    assert f[2] == np.exp(-m[2]) and np.all(np.delete(f, 2) == 1.0)
    assert np.all(scale_corrections(X, C, T_WC, C_CONF_THRESHOLD, tolerance=0.0) == 1.0)
