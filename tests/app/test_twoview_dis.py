"""DIS flow of the two-view prior: the finest pyramid level is chosen by the flows' own
forward-backward consistency (``mslam.priors.twoview_dis``)."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import FLOW_GAIN_SHORTFALL

from mslam.datasets.synthetic import make_sequence
from mslam.priors import twoview_dis
from mslam.priors.twoview_geometry import forward_backward_error
from mslam_ref import sim3
from mslam_ref.pointmap import backproject, project

W, H = 160, 120


@pytest.fixture(scope="module")
def forward():
    return make_sequence("forward", n_frames=120, width=W, height=H, seed=0)


def _true_flow(seq, i: int, j: int) -> np.ndarray:
    fi, fj = seq[i], seq[j]
    X = backproject(fi.depth, seq.K).reshape(-1, 3)
    uv_j, _ = project(sim3.act(sim3.mul(sim3.inv(fj.T_WC), fi.T_WC), X), seq.K)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    return uv_j.reshape(H, W, 2) - np.stack([u, v], -1)


def _gain(F: np.ndarray, B: np.ndarray, true: np.ndarray) -> float:
    """Least-squares factor of the true flow in F, over the pixels where the flow F, B is
    consistent (forward-backward error < 1 px) and the true flow is finite."""
    ok = np.isfinite(true).all(-1) & (forward_backward_error(F, B)[0] < 1.0)
    return float(np.sum(F[ok] * true[ok]) / np.sum(true[ok] ** 2))


def test_chosen_flow_is_not_shortened_like_the_half_resolution_preset(forward) -> None:
    """The preset stops at half resolution and comes out short; the chosen scale does not."""
    gains, preset = [], []
    for i, j in [(0, 3), (0, 6), (30, 36), (60, 66), (90, 100)]:
        true = _true_flow(forward, i, j)
        gi, gj = (twoview_dis._grey(forward[k].rgb) for k in (i, j))
        gains.append(_gain(*twoview_dis._dis_both_ways(gi, gj, None, None), true))
        preset.append(_gain(*twoview_dis._dis_at(gi, gj, None, None, 1), true))
    assert min(gains) > 1 - FLOW_GAIN_SHORTFALL, gains
    assert np.mean(np.abs(1 - np.array(preset))) > np.mean(np.abs(1 - np.array(gains)))


def test_the_more_consistent_scale_wins(forward) -> None:
    gi, gj = (twoview_dis._grey(forward[k].rgb) for k in (0, 6))
    shares = {}
    for scale in twoview_dis.FINEST_SCALES:
        F, B = twoview_dis._dis_at(gi, gj, None, None, scale)
        shares[scale] = float(np.mean(forward_backward_error(F, B)[0] < twoview_dis.SCALE_FB_PX))
    F_ij, F_ji = twoview_dis._dis_both_ways(gi, gj, None, None)
    chosen = float(np.mean(forward_backward_error(F_ij, F_ji)[0] < twoview_dis.SCALE_FB_PX))
    assert chosen == max(shares.values())


def test_focal_guess_spans_the_long_side() -> None:
    """A portrait frame is a landscape camera turned upright: the same focal length."""
    from mslam.priors.twoview_geometry import focal_guess_intrinsics

    land, port = focal_guess_intrinsics(160, 120), focal_guess_intrinsics(120, 160)
    assert port[0, 0] == port[1, 1] == land[0, 0]
    assert (port[0, 2], port[1, 2]) == (land[1, 2], land[0, 2])
