"""Optical flow under an exposure change: the gain measured along the flow and removed."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import (
    EXPOSURE_GAIN_REL,
    EXPOSURE_ROUNDING_LEVELS,
    FLOW_ACCURATE_PX,
    FLOW_UNDER_GAIN_SHARE,
)

from mslam.datasets.synthetic import make_sequence
from mslam.priors import photometric
from mslam.priors.twoview_dis import _dis_both_ways, _grey, dense_flow
from mslam_ref import sim3
from mslam_ref.pointmap import backproject, project

W, H = 160, 120
#: Border (pixels) left out of flow comparisons (DIS extrapolates there).
BORDER = 8


@pytest.fixture(scope="module")
def seq():
    # The forward path at 160x120: ~8 cm and ~1° between neighbours.
    return make_sequence("forward", n_frames=16, width=W, height=H, seed=0)


def _true_flow(seq, i: int, j: int) -> np.ndarray:
    """(H, W, 2) flow from frame i to frame j from the true depth and poses."""
    T_ji = sim3.mul(sim3.inv(seq[j].T_WC), seq[i].T_WC)
    X = backproject(seq[i].depth, seq.K).reshape(-1, 3)
    uv, _ = project(sim3.act(T_ji, X), seq.K)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    return uv.reshape(H, W, 2) - np.stack([u, v], axis=-1)


def _with_gain(rgb: np.ndarray, gain: float) -> np.ndarray:
    return np.clip(rgb.astype(np.float64) * gain, 0, 255).astype(np.uint8)


def _accurate_share(F: np.ndarray, F_true: np.ndarray) -> float:
    err = np.linalg.norm(F - F_true, axis=-1)[BORDER:-BORDER, BORDER:-BORDER]
    return float(np.mean(err < FLOW_ACCURATE_PX))


@pytest.mark.parametrize("gain", [0.6, 1.5])
def test_exposure_gain_is_measured_along_the_flow(seq, gain):
    F_true = _true_flow(seq, 0, 2)
    gi, gj = _grey(seq[0].rgb), _grey(_with_gain(seq[2].rgb, gain))
    g = photometric.exposure_gain(gi, gj, F_true, np.zeros((H, W)))
    assert abs(g / gain - 1) < EXPOSURE_GAIN_REL
    # No consistent pixel: no measurement, gain 1.
    assert photometric.exposure_gain(gi, gj, F_true, np.full((H, W), np.inf)) == 1.0


def test_common_exposure_equalises_and_is_symmetric(seq):
    gi = _grey(seq[0].rgb)
    gj = _grey(_with_gain(seq[0].rgb, 0.5))
    a, b = photometric.common_exposure(gi, gj, 0.5)
    # The same image at two exposures: apart by rounding only after the alignment (the dark
    # copy's levels are truncated, then scaled up by sqrt(2)).
    assert np.abs(a.astype(int) - b.astype(int)).max() <= EXPOSURE_ROUNDING_LEVELS
    assert np.abs(gi.astype(int) - gj.astype(int)).max() > EXPOSURE_ROUNDING_LEVELS
    b2, a2 = photometric.common_exposure(gj, gi, 2.0)
    assert np.array_equal(a, a2) and np.array_equal(b, b2)
    with pytest.raises(ValueError, match="gain"):
        photometric.common_exposure(gi, gj, 0.0)


@pytest.mark.parametrize(("i", "j"), [(0, 2), (10, 13)])
@pytest.mark.parametrize("gain", [0.5, 1.8])
def test_flow_under_a_gain_is_as_good_as_without(seq, i, j, gain):
    F_true = _true_flow(seq, i, j)
    plain = _accurate_share(dense_flow(seq[i].rgb, seq[j].rgb)[0], F_true)
    gained = _accurate_share(dense_flow(seq[i].rgb, _with_gain(seq[j].rgb, gain))[0], F_true)
    assert gained > plain - FLOW_UNDER_GAIN_SHARE


def test_flow_without_a_gain_is_plain_dis(seq):
    """Images of one exposure: the flow is DIS's on the raw grey levels, bit for bit (at the
    finest scale the flows' consistency chooses, ``twoview_dis``)."""
    gi, gj = _grey(seq[0].rgb), _grey(seq[2].rgb)
    F_ij, F_ji = dense_flow(seq[0].rgb, seq[2].rgb)
    P_ij, P_ji = _dis_both_ways(gi, gj, None, None)
    assert np.array_equal(F_ij, P_ij) and np.array_equal(F_ji, P_ji)
