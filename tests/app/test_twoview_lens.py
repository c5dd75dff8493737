"""The radial distortion of an uncalibrated video, from the video (``mslam.priors.twoview_lens``).

* the division model's point undistortion and its remap tables are inverses of each other;
* the residual of a least-squares fundamental matrix is smallest at the lens's own division
  coefficient (exact two-view geometry distorted by a known lens), and at zero for a pinhole;
* the decision uses an estimate only when the pinhole explains the flow clearly worse, the
  bootstrap keeps zero out, enough pairs entered and the minimum is not at an end of the span;
* on a rendered video distorted by a known lens the pre-pass finds the lens, and the run then
  undistorts its frames; the same video undistorted keeps the pinhole.
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import LENS_LAMBDA_ABS

from mslam.config import load_config
from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.images import division_maps, division_undistort_points
from mslam.datasets.synthetic import make_sequence
from mslam.datasets.views import DivisionUndistortedSequence
from mslam.priors.twoview_focal import estimate_focal
from mslam.priors.twoview_lens import LAMBDAS, MIN_GAIN, MIN_PAIRS, decide_lens, residual_curve
from mslam.system import open_source
from mslam.system.sources import self_calibrate
from mslam_ref import so3

W, H = 160, 120


@pytest.mark.parametrize("lam", [-0.2, -0.05, 0.1])
def test_division_maps_invert_the_point_undistortion(lam: float) -> None:
    mx, my = division_maps(lam, W, H)
    v, u = np.mgrid[0:H:7, 0:W:9]
    distorted = np.stack([mx[v, u], my[v, u]], -1).reshape(-1, 2).astype(np.float64)
    back = division_undistort_points(distorted, lam, W, H)
    grid = np.stack([u, v], -1).reshape(-1, 2)
    assert np.max(np.abs(back - grid)) < 1e-3
    assert np.array_equal(division_undistort_points(grid, 0.0, W, H), grid)


def _distort(uv: np.ndarray, lam: float) -> np.ndarray:
    """Pixels of a pinhole camera seen through the division-model lens ``lam`` (inverted by
    fixed-point iteration: the distorted point whose undistortion is ``uv``)."""
    d = uv.copy()
    for _ in range(50):
        d = d + (uv - division_undistort_points(d, lam, W, H))
    return d


def _pair(lam: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-1.5, 1.5, 600), rng.uniform(-1.0, 1.0, 600), rng.uniform(2, 5, 600)]
    K = np.array([[120.0, 0, (W - 1) / 2], [0, 120.0, (H - 1) / 2], [0, 0, 1]])
    R = so3.to_matrix(so3.exp(np.radians([2.0, -3.0, 1.0])))
    t = np.array([0.25, 0.05, 0.05])
    uv = [(K @ Y.T).T for Y in (X, X @ R.T + t)]
    uv_i, uv_j = (p[:, :2] / p[:, 2:] for p in uv)
    inside = np.all((uv_i > 0) & (uv_i < [W, H]) & (uv_j > 0) & (uv_j < [W, H]), 1)
    return _distort(uv_i[inside], lam), _distort(uv_j[inside], lam)


@pytest.mark.parametrize("lam", [-0.15, 0.0, 0.1])
def test_residual_is_least_at_the_lens_of_the_flow(lam: float) -> None:
    curve = residual_curve(*_pair(lam), W, H)
    assert curve is not None
    assert abs(LAMBDAS[int(np.argmin(curve))] - lam) <= LENS_LAMBDA_ABS
    if lam:  # the pinhole model cannot explain distorted flow
        assert curve[int(np.argmin(np.abs(LAMBDAS)))] > MIN_GAIN * curve.min()


def _curves(centres: np.ndarray, depth: float = 1.0) -> np.ndarray:
    """V-shaped residual curves (P, len(LAMBDAS)) ``1 + depth |λ - centre|`` per pair."""
    return 1.0 + depth * np.abs(LAMBDAS[None, :] - centres[:, None])


def test_decision_uses_a_clear_lens_only() -> None:
    rng = np.random.default_rng(1)
    clear = decide_lens(_curves(-0.1 + rng.normal(0, 0.01, 30), depth=8.0))
    assert clear.used and clear.lam_in_use == pytest.approx(-0.1, abs=LENS_LAMBDA_ABS)
    shallow = decide_lens(_curves(-0.1 + rng.normal(0, 0.01, 30), depth=0.5))
    assert not shallow.used and shallow.lam_in_use == 0.0 and shallow.gain < MIN_GAIN
    scattered = decide_lens(_curves(rng.uniform(-0.25, 0.25, 30), depth=8.0))
    assert not scattered.used
    few = decide_lens(_curves(np.full(MIN_PAIRS - 1, 0.1), depth=8.0))
    assert not few.used and few.lam is None
    at_end = decide_lens(_curves(np.full(30, 0.5), depth=8.0))
    assert not at_end.used


class _Distorted(FrameSequence):
    """A sequence seen through the division-model lens ``lam``."""

    def __init__(self, base: FrameSequence, lam: float) -> None:
        self.base, self.name = base, f"{base.name} distorted"
        self.timestamps, self.T_WC = base.timestamps, base.T_WC
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        src = division_undistort_points(np.stack([u, v], -1).reshape(-1, 2), lam, W, H)
        self.maps = [m.reshape(H, W).astype(np.float32) for m in src.T]

    def _load(self, i: int) -> Frame:
        import cv2

        f = self.base[i]
        rgb = cv2.remap(f.rgb, *self.maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return Frame(index=f.index, timestamp=f.timestamp, rgb=rgb)


def test_a_distorted_video_gets_its_lens_and_is_undistorted() -> None:
    base = make_sequence("loop", n_frames=60, width=W, height=H, seed=0)
    lam = -0.15
    est = estimate_focal(_Distorted(base, lam))
    assert est.lens is not None and est.lens.used, est.lens
    assert abs(est.lens.lam_in_use - lam) <= 2 * LENS_LAMBDA_ABS
    src = open_source("synthetic:loop:60:160x120", load_config("twoview", []), None, "twoview")
    src.sequence = _Distorted(src.sequence, lam)
    record = self_calibrate(src)
    assert record is not None and record["lens"]["used"]  # type: ignore[index]
    assert isinstance(src.sequence, DivisionUndistortedSequence)
    assert src.sequence[5].rgb.shape == (H, W, 3)
    pinhole = estimate_focal(base)
    assert pinhole.lens is not None and not pinhole.lens.used
