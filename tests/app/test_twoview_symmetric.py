"""Two-view prior: one correspondence per point for both views (symmetric flow), and pointmaps
that stay consistent when the images are compressed."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from tolerances import FLOW_PX, MATCH_SHARE_UNDER_JPEG

from mslam.datasets.synthetic import make_sequence
from mslam.priors.twoview import TwoViewPrior
from mslam.priors.twoview_geometry import forward_backward_error, symmetric_flow
from mslam_ref import matching

W, H = 128, 96
#: (keyframe, frame) pairs of the forward path, 2-4 frames apart (0.9-2.2° of triangulation).
PAIRS = ((0, 2), (0, 4), (10, 14), (30, 33))


@pytest.fixture(scope="module")
def seq():
    return make_sequence("forward", n_frames=34, width=W, height=H, seed=0)


def _translation_flows(dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    F_ij = np.broadcast_to(np.array([dx, dy]), (H, W, 2)).copy()
    return F_ij, -F_ij


def test_symmetric_flow_keeps_a_consistent_flow():
    F_ij, F_ji = _translation_flows(1.25, -0.5)
    np.testing.assert_allclose(symmetric_flow(F_ij, F_ji), F_ij, atol=FLOW_PX)


def test_symmetric_flow_halves_a_forward_backward_disagreement():
    F_ij, F_ji = _translation_flows(1.25, -0.5)
    noisy = F_ij + np.array([0.4, 0.2])
    sym = symmetric_flow(noisy, F_ji)
    inside = forward_backward_error(noisy, F_ji)[1]
    np.testing.assert_allclose(sym[inside], (F_ij + np.array([0.2, 0.1]))[inside], atol=FLOW_PX)
    # Where the flow leaves the other image there is no backward flow: the flow is kept.
    assert (~inside).any()
    np.testing.assert_array_equal(sym[~inside], noisy[~inside])


def _jpeg(rgb: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, quality])  # fmt: skip
    assert ok
    return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])


def _match_share(seq, quality: int | None) -> float:
    """Mean share of keyframe pixels whose point in the frame's camera meets the frame's own
    point (``matching.match`` valid) over :data:`PAIRS`."""
    prior, shares = TwoViewPrior(), []
    for k, f in PAIRS:
        frame, kf = seq[f], seq[k]
        if quality is not None:
            frame = dataclasses.replace(frame, rgb=_jpeg(frame.rgb, quality))
            kf = dataclasses.replace(kf, rgb=_jpeg(kf.rgb, quality))
        p = prior.pair(frame, kf)
        assert prior.last_status == "ok"
        _, valid = matching.match(p.X_ii, p.X_ji, p.D_ii, p.D_ji, None, matching.MatchingConfig())
        shares.append(float(np.mean(valid)))
    return float(np.mean(shares))


def test_compression_keeps_the_two_pointmaps_of_a_pair_consistent(seq):
    # The keyframe test counts these matches: a compressed copy must not lose many of them
    # (the two views of a pair, triangulated from separate flows, disagreed by more than the
    # matching's distance threshold where the flow is noisy).
    clean, jpeg = _match_share(seq, None), _match_share(seq, 8)
    assert jpeg >= clean - MATCH_SHARE_UNDER_JPEG
