"""The focal length of an uncalibrated video, from the video (``mslam.priors.twoview_focal``).

* the self-calibration cost of an exact fundamental matrix vanishes at the camera's focal
  length and nowhere else in the searched span;
* the decision uses an estimate only when the pairs agree on it (a bootstrap over pairs),
  when enough pairs entered, away from the ends of the span, and outside the estimator's
  long bias above the guess;
* on a rendered video of a 70° camera the estimate is used and lies closer to the camera's
  focal length than the 60° guess; a camera that only turns has no epipolar geometry and
  keeps the guess;
* ``twoview_prior.self_calibrate: false`` keeps the guess without a pre-pass.
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import FOCAL_ESTIMATE_REL

from mslam.config import load_config
from mslam.datasets.synthetic import make_sequence
from mslam.priors.twoview_focal import (
    LONG_BIAS,
    MIN_PAIRS,
    SEARCH,
    decide,
    estimate_focal,
    kruppa_cost,
)
from mslam.priors.twoview_geometry import focal_guess_intrinsics
from mslam.system import open_source
from mslam.system.sources import self_calibrate
from mslam_ref import so3

W, H = 160, 120


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


@pytest.mark.parametrize("true_scale", [0.7, 1.0, 1.3])
def test_kruppa_cost_vanishes_at_the_true_focal_length(true_scale: float) -> None:
    K_guess = focal_guess_intrinsics(W, H)
    K = K_guess.copy()
    K[0, 0] *= true_scale
    K[1, 1] *= true_scale
    R = so3.to_matrix(so3.exp(np.radians([4.0, -7.0, 2.0])))
    t = np.array([0.6, 0.2, 0.3])
    F = np.linalg.inv(K).T @ _skew(t) @ R @ np.linalg.inv(K)
    F = F / np.linalg.norm(F)
    assert kruppa_cost(F, K_guess, np.array([true_scale]))[0] < 1e-9
    cost = kruppa_cost(F, K_guess)
    step = SEARCH[1] / SEARCH[0]
    assert abs(np.log(SEARCH[int(np.argmin(cost))] / true_scale)) <= np.log(step)
    far = np.abs(np.log(SEARCH / true_scale)) > 2 * np.log(step)
    assert np.min(cost[far]) > 1e-4


def _curves(centres: np.ndarray) -> np.ndarray:
    """V-shaped cost curves (P, len(SEARCH)) with minima at the given factors."""
    return np.abs(np.log(SEARCH)[None, :] - np.log(centres)[:, None])


def test_decision_uses_an_agreed_estimate_only() -> None:
    rng = np.random.default_rng(1)
    agreed = decide(_curves(1.25 * np.exp(rng.normal(0, 0.03, 30))), 100.0, 0)
    assert agreed.used and abs(agreed.estimate_px / 125.0 - 1) < 0.05
    assert agreed.scale == pytest.approx(agreed.estimate_px / 100.0)
    scattered = decide(_curves(np.exp(rng.uniform(-0.5, 0.5, 30))), 100.0, 0)
    assert not scattered.used and scattered.scale == 1.0
    few = decide(_curves(np.full(MIN_PAIRS - 1, 1.25)), 100.0, 0)
    assert not few.used and few.estimate_px is None
    at_end = decide(_curves(np.full(30, 5.0)), 100.0, 0)
    assert not at_end.used
    shorter = decide(_curves(0.85 * np.exp(rng.normal(0, 0.03, 30))), 100.0, 0)
    assert shorter.used and shorter.estimate_px < 100.0
    # a little longer than the guess: within the estimator's own long bias
    near = decide(_curves(np.sqrt(LONG_BIAS) * np.exp(rng.normal(0, 0.01, 30))), 100.0, 0)
    assert near.high_px < 100.0 * LONG_BIAS * 1.05 and not near.used


def test_a_70_degree_video_gets_its_focal_length() -> None:
    seq = make_sequence("loop", n_frames=72, width=128, height=96, seed=0)
    est = estimate_focal(seq)
    f_true, guess = float(seq.K[0, 0]), focal_guess_intrinsics(128, 96)[0, 0]
    assert est.used, est.reason
    assert abs(est.estimate_px / f_true - 1) <= FOCAL_ESTIMATE_REL
    assert abs(est.estimate_px - f_true) < abs(guess - f_true)


def test_pure_rotation_keeps_the_guess() -> None:
    est = estimate_focal(make_sequence("rotation", n_frames=40, width=96, height=72, seed=0))
    assert not est.used and est.scale == 1.0


@pytest.mark.parametrize("on", [True, False])
def test_the_setting_turns_the_pre_pass_off(on: bool) -> None:
    keys = [] if on else ["twoview_prior.self_calibrate=false"]
    src = open_source("synthetic:loop:40:96x72", load_config("twoview", keys), None, "twoview")
    record = self_calibrate(src)
    assert (record is not None) is on
    assert self_calibrate(src) is None or not on  # a second call leaves a set prior alone
