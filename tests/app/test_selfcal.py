"""The camera of an uncalibrated video from many views (``mslam.priors.twoview_selfcal``).

* the shared-camera bundle adjustment recovers a focal length and a radial coefficient from
  noisy observations, within its own stated uncertainty, and leaves them alone when fixed;
* the incremental reconstruction of one stretch finds the camera from point tracks alone,
  starting from the 60° guess, and refuses a camera that only turns (no starting pair);
* the decision uses the stretches' mean only when enough of them reconstruct, each is
  determined and they agree;
* the division coefficient that stands in for the forward lens model undistorts its points;
* tracks follow a moving image, and the detail frames come from the source's own resolution;
* on a rendered video the whole estimate lands near the true focal length, and a run then
  takes it (``self_calibrate``).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from tolerances import SELFCAL_FOCAL_REL, SELFCAL_K_ABS, TRACK_SHIFT_PX

from mslam.config import load_config
from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.images import division_undistort_points
from mslam.datasets.views import DivisionUndistortedSequence, ResizedSequence
from mslam.priors.selfcal_ba import Problem, Solution, bundle_adjust, camera_covariance
from mslam.priors.selfcal_sfm import Reconstruction, reconstruct
from mslam.priors.selfcal_tracks import DETAIL_SIDE, Tracks, detail_frames, track
from mslam.priors.twoview_selfcal import (
    AGREE_F,
    MAX_SD_F,
    STRETCH_FRAMES,
    decide_camera,
    division_coefficient,
    estimate_camera,
    stretches,
)
from mslam.system import open_source
from mslam.system.sources import self_calibrate
from mslam_ref import so3

W, H = 320, 240
C = np.array([(W - 1) / 2, (H - 1) / 2])
S = 0.5 * np.hypot(W, H)
#: The 60° guess over the half diagonal, and a 70° camera's.
F_GUESS = (W / 2) / np.tan(np.radians(30.0)) / S
F_TRUE = (W / 2) / np.tan(np.radians(35.0)) / S


def _scene(n_views: int, k: float, noise: float, turn: bool = False, seed: int = 0):
    """Points in front of a camera moving sideways and turning (or only turning); the pixels
    of every point in every view through (F_TRUE, k), with Gaussian noise."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-4, 4, 1500), rng.uniform(-3, 3, 1500), rng.uniform(2.5, 6, 1500)]
    a = np.linspace(0, 1, n_views)
    R = so3.to_matrix(so3.exp(np.stack([0.08 * np.sin(3 * a), 0.25 * np.sin(2 * a), 0.05 * a], 1)))
    centres = (
        np.zeros((n_views, 3)) if turn else np.stack([0.8 * a, 0.15 * np.sin(4 * a), 0.1 * a], 1)
    )
    t = -np.einsum("vij,vj->vi", R, centres)
    X_c = np.einsum("vij,pj->vpi", R, X) + t[:, None]
    x_u = F_TRUE * X_c[..., :2] / X_c[..., 2:]
    uv = C + S * x_u * (1 + k * (x_u * x_u).sum(-1, keepdims=True))
    uv = uv + rng.normal(0, noise, uv.shape)
    seen = np.all((uv > 0) & (uv < [W - 1, H - 1]), -1) & (X_c[..., 2] > 0)
    return R, t, X, uv, seen


def test_bundle_adjustment_recovers_a_shared_camera() -> None:
    k, noise = -0.04, 0.2
    R, t, X, uv, seen = _scene(30, k, noise)
    v, p = np.nonzero(seen)
    prob = Problem(v, p, uv[v, p], C, S)
    rng = np.random.default_rng(1)
    R0 = so3.to_matrix(so3.exp(rng.normal(0, 0.01, (len(R), 3)))) @ R
    R0[0] = R[0]
    t0 = t + rng.normal(0, 0.02, t.shape)
    t0[0] = t[0]
    x, _ = bundle_adjust(prob, Solution(R0, t0, X + rng.normal(0, 0.05, X.shape), F_GUESS, 0.0),
                         np.array([0]), camera=True, iterations=60)  # fmt: skip
    sd = np.sqrt(np.diag(camera_covariance(prob, x, np.array([0])))) * noise
    assert abs(np.log(x.F / F_TRUE)) < 4 * sd[0] and abs(x.k - k) < 4 * sd[1]
    assert sd[0] < 0.01 and sd[1] < 0.005  # a well-posed scene is determined
    fixed, _ = bundle_adjust(prob, Solution(R0, t0, X, F_GUESS, 0.0), np.array([0]), camera=False)
    assert fixed.F == F_GUESS and fixed.k == 0.0


def _tracks(uv: np.ndarray, seen: np.ndarray) -> Tracks:
    v, p = np.nonzero(seen)
    return Tracks(p, v, uv[v, p], (W, H))


@pytest.mark.parametrize("k", [0.0, -0.05])
def test_a_stretch_gives_its_camera(k: float) -> None:
    *_, uv, seen = _scene(40, k, 0.2)
    rec = reconstruct(_tracks(uv, seen), np.arange(0, 40, 2), F_GUESS)
    assert rec is not None and rec.views == rec.views_total == 20
    assert abs(rec.F / F_TRUE - 1) < SELFCAL_FOCAL_REL and abs(rec.k - k) < SELFCAL_K_ABS
    assert np.sqrt(rec.cov[0, 0]) < MAX_SD_F and rec.sigma_px < 0.5


def test_a_camera_that_only_turns_has_no_reconstruction() -> None:
    *_, uv, seen = _scene(40, 0.0, 0.2, turn=True)
    assert reconstruct(_tracks(uv, seen), np.arange(0, 40, 2), F_GUESS) is None


def _rec(F: float, k: float, sd_f: float = 0.01) -> tuple[Reconstruction, float]:
    return Reconstruction(F, k, np.diag([sd_f**2, 0.003**2]), 0.3, 25, 25, 500), 1.0


def test_the_stretches_must_agree() -> None:
    ranges = [(0, 75), (75, 150)]
    used = decide_camera(ranges, [_rec(0.90, -0.03), _rec(0.92, -0.02)])
    assert used.used and used.focal_scale == pytest.approx(np.sqrt(0.90 * 0.92))
    assert used.k == pytest.approx(-0.025) and used.lam == division_coefficient(-0.025)
    apart = decide_camera(ranges, [_rec(0.90, -0.03), _rec(0.90 * np.exp(1.5 * AGREE_F), -0.03)])
    assert not apart.used and apart.focal_scale == 1.0 and apart.lam == 0.0
    loose = decide_camera(ranges, [_rec(0.90, -0.03, 2 * MAX_SD_F), _rec(0.90, -0.03)])
    assert not loose.used
    alone = decide_camera(ranges, [_rec(0.90, -0.03), (None, 1.0)])
    assert not alone.used and alone.stretches[1] == {"frames": [75, 150], "reconstructed": False}


def test_stretches_spread_over_the_video() -> None:
    assert stretches(150) == [(0, 75), (75, 150)]
    assert stretches(40) == []  # stretches of 20 frames are too short
    long = stretches(1000)
    assert len(long) == 2 and all(b - a == STRETCH_FRAMES for a, b in long)
    assert long[0][0] > 0 and long[1][1] < 1000  # centred in their halves


@pytest.mark.parametrize("k", [-0.1, -0.03, 0.05])
def test_the_division_model_stands_in_for_the_lens(k: float) -> None:
    x_u = np.stack(np.meshgrid(np.linspace(-0.8, 0.8, 9), np.linspace(-0.6, 0.6, 7)), -1)
    x_u = x_u.reshape(-1, 2)
    uv_d = C + S * x_u * (1 + k * (x_u * x_u).sum(1, keepdims=True))
    back = division_undistort_points(uv_d, division_coefficient(k), W, H)
    # within 5 % of the lens's own displacement at the corner (|k| · S, 20 px for k = -0.1)
    assert np.max(np.linalg.norm(back - (C + S * x_u), axis=1)) < 0.05 * abs(k) * S


def test_tracks_follow_a_moving_image() -> None:
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (300, 400)).astype(np.float32), (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    shift = np.array([1.5, -0.7])
    grays = [cv2.warpAffine(tex, np.float32([[1, 0, 40 + n * shift[0]], [0, 1, 30 + n * shift[1]]]),
                            (W, H)) for n in range(6)]  # fmt: skip
    tr = track(grays)
    first = {(i, f): uv for i, f, uv in zip(tr.track, tr.frame, tr.uv, strict=True)}
    steps = [uv - first[(i, f - 1)] for i, f, uv in zip(tr.track, tr.frame, tr.uv, strict=True)
             if f and (i, f - 1) in first]  # fmt: skip
    assert len(steps) > 500 and tr.size == (W, H)
    assert np.all(np.abs(np.median(steps, axis=0) - shift) < TRACK_SHIFT_PX)


class _Plain(FrameSequence):
    """Flat-grey frames of a given size."""

    def __init__(self, w: int, h: int, n: int = 4) -> None:
        self.w, self.h, self.name = w, h, "plain"
        self.timestamps, self.T_WC = np.arange(n) / 30.0, None

    def _load(self, i: int) -> Frame:
        return Frame(i, i / 30.0, np.full((self.h, self.w, 3), 90 + i, np.uint8))


def test_detail_frames_come_from_the_source() -> None:
    small = ResizedSequence(_Plain(640, 480), 160, 120, (640, 480))
    assert detail_frames(small)(2).shape == (240, 320)
    assert detail_frames(small)(2)[0, 0] == 92  # the frame asked for
    assert detail_frames(_Plain(200, 150))(0).shape == (150, 200)  # never enlarged
    est = estimate_camera(_Plain(200, 150, 100))
    assert not est.used and f"< {DETAIL_SIDE}" in est.reason


class _Blobs(FrameSequence):
    """A video of 1500 coloured discs scattered through a room's depth, seen by the camera of
    :func:`_scene` (a 70° lens with radial coefficient ``k``) moving sideways and turning."""

    def __init__(self, n: int, k: float) -> None:
        R, t, X, uv, _ = _scene(n, k, 0.0)
        rng = np.random.default_rng(5)
        self.name, self.timestamps, self.T_WC = "blobs", np.arange(n) / 30.0, None
        self.X_c = np.einsum("vij,pj->vpi", R, X) + t[:, None]
        self.uv, self.colours = uv, rng.integers(30, 226, (len(X), 3))

    def _load(self, i: int) -> Frame:
        img = np.full((H, W, 3), 128, np.uint8)
        for p in np.argsort(-self.X_c[i, :, 2]):  # far discs first
            z = self.X_c[i, p, 2]
            if z > 0 and np.all((self.uv[i, p] > -5) & (self.uv[i, p] < [W + 5, H + 5])):
                centre = tuple(round(c * 16) for c in self.uv[i, p])
                cv2.circle(img, centre, int(16 * 18 / z), self.colours[p].tolist(), -1,
                           cv2.LINE_AA, 4)  # fmt: skip
        return Frame(i, i / 30.0, img)


@pytest.mark.slow
@pytest.mark.parametrize("k", [0.0, -0.05])
def test_a_rendered_video_gets_its_camera(k: float) -> None:
    video = ResizedSequence(_Blobs(120, k), 160, 120, (W, H))
    est = estimate_camera(video)
    assert est.used, est.reason
    assert abs(est.focal_scale * F_GUESS / F_TRUE - 1) < SELFCAL_FOCAL_REL
    assert abs(est.k - k) < SELFCAL_K_ABS


def test_a_run_takes_the_camera_from_many_views() -> None:
    src = open_source("synthetic:loop:40:320x240", load_config("twoview", []), None, "twoview")
    src.sequence = ResizedSequence(_Blobs(120, -0.05), 160, 120, (W, H))
    record = self_calibrate(src)
    assert record is not None and record["method"] == "many views" and record["used"]
    assert src.prior.focal_scale == record["scale"] != 1.0  # type: ignore[attr-defined]
    assert record["lens"]["lam_in_use"] < 0  # type: ignore[index]
    assert isinstance(src.sequence, DivisionUndistortedSequence)
