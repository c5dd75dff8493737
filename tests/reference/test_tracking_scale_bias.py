"""The tracking solve's scale under noise in the distances (paper §3.3, the distance residual).

``r_dist = ‖X_k‖ − ‖T_CkCf X_f‖``: the scale of ``T_CkCf`` multiplies the frame's distances.
Zero-mean noise in the keyframe's distances (the regressand) leaves the scale unbiased; the
same noise in the frame's distances (the regressor) shrinks it, as least squares does with
noise in a regressor (regression dilution: relative noise sigma 0.3 gives
``s ≈ 1 / (1 + σ²) ≈ 0.92``). A two-view prior's frame pointmap is one noisy pair, the
keyframe's a fusion of many, so each tracked frame and each keyframe made from one sits too
close; on the kitchen clip with noise of 15 grey levels per pixel at 160x120 the median of
``log(‖X_k‖ / ‖T_CkCf X_f‖)`` after a solve was +0.11 (+0.04 without noise) and the map's
scale shrank 7-fold over 8 keyframes (2026-11-27). A log-distance residual,
``log‖X_k‖ − log‖T_CkCf X_f‖``, is no cure: with this additive noise it gives
``|log s| = 0.050`` whichever side is noisy, and on that clip it brought the median to −0.005
while the map still shrank 10.5-fold (docs/priors.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import TRACKING_SCALE_BIAS_LOG

from mslam_ref import sim3, tracking
from mslam_ref.tracking import TrackingConfig

N = 5000
#: relative noise of the noisy side's distances (zero mean, clipped symmetrically at CLIP)
SIGMA_REL = 0.3
CLIP = 0.8


def _points(rng: np.random.Generator) -> np.ndarray:
    """(N, 3) points in front of the camera at distances 1-3."""
    d = rng.normal(size=(N, 3)) * [0.4, 0.3, 0.0] + [0.0, 0.0, 1.0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(1.0, 3.0, (N, 1))


def _solved_log_scale(noisy: str) -> float:
    """log s of ``T_CkCf`` solved from identity, true pose identity, with zero-mean relative
    noise along the rays in the distances of ``noisy`` (``"frame"`` or ``"keyframe"``)."""
    rng = np.random.default_rng(0)
    X = _points(rng)
    X_noisy = X * (1.0 + np.clip(rng.normal(0.0, SIGMA_REL, (N, 1)), -CLIP, CLIP))
    X_f, X_k = (X_noisy, X) if noisy == "frame" else (X, X_noisy)
    T, info = tracking.solve(
        X_f, X_k, np.ones(N), np.ones(N, bool), sim3.identity(), TrackingConfig()
    )
    assert not info.failed
    return float(np.log(T[7]))


def test_noise_in_the_keyframe_distances_leaves_the_scale_unbiased() -> None:
    assert abs(_solved_log_scale("keyframe")) < TRACKING_SCALE_BIAS_LOG


@pytest.mark.xfail(
    strict=True,
    reason="the distance residual's least squares dilutes the scale by noise in the frame's "
    "distances (s ~ 1 / (1 + sigma^2)): tracked frames sit too close under image noise "
    "(docs/priors.md)",
)
def test_noise_in_the_frame_distances_leaves_the_scale_unbiased() -> None:
    assert abs(_solved_log_scale("frame")) < TRACKING_SCALE_BIAS_LOG
