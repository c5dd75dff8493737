"""Calibrated RGB-only input: intrinsics after the working-resolution resize, and the pixels
of the two-view prior that take part in the pose solves."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import PAIR_SCALE_REL, RESIZE_CENTROID_PX

from mslam.config import load_config
from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.synthetic import make_sequence
from mslam.datasets.views import ResizedSequence
from mslam.priors.twoview import TwoViewPrior, TwoViewPriorConfig
from mslam_ref import fusion, sim3, tracking
from mslam_ref.pointmap import backproject, scale_intrinsics

#: A 640x480 camera (7-Scenes' nominal intrinsics) and a point seen at a sub-pixel position.
K_FULL = np.array([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
X_POINT = np.array([0.137, -0.091, 1.7])


class _BlobSequence(FrameSequence):
    """One 640x480 frame: a Gaussian blob (sigma 6 px) centred on ``X_POINT``'s projection."""

    def __init__(self) -> None:
        self.timestamps = np.zeros(1)
        self.K = K_FULL

    def _load(self, i: int) -> Frame:
        u0, v0 = (K_FULL @ X_POINT)[:2] / X_POINT[2]
        v, u = np.mgrid[0:480, 0:640].astype(np.float64)
        g = 250.0 * np.exp(-((u - u0) ** 2 + (v - v0) ** 2) / (2 * 6.0**2))
        return Frame(0, 0.0, np.repeat(np.round(g).astype(np.uint8)[..., None], 3, axis=-1))


def _centroid(img: np.ndarray) -> np.ndarray:
    w = img[..., 0].astype(np.float64)
    v, u = np.mgrid[0 : w.shape[0], 0 : w.shape[1]].astype(np.float64)
    return np.array([(u * w).sum(), (v * w).sum()]) / w.sum()


def test_resized_intrinsics_project_where_the_resized_image_shows_the_point():
    seq = ResizedSequence(_BlobSequence(), 160, 120, (640, 480))
    K = seq.K
    assert K is not None
    np.testing.assert_allclose(K[[0, 1, 0, 1], [0, 1, 2, 2]], [146.25, 146.25, 79.625, 59.625])
    seen = _centroid(seq[0].rgb)
    predicted = (K @ X_POINT)[:2] / X_POINT[2]
    assert np.max(np.abs(seen - predicted)) < RESIZE_CENTROID_PX
    # The plain multiplication of the principal point (no pixel-centre shift) misses by 3/8 px.
    K_plain = scale_intrinsics(K_FULL, (640, 480), (160, 120), half_pixel=False)
    assert np.min(np.abs(seen - (K_plain @ X_POINT)[:2] / X_POINT[2])) > RESIZE_CENTROID_PX


@pytest.fixture(scope="module")
def loop_pair():
    """Frame 5 and keyframe 0 of the synthetic loop (160x120, ~20° apart: some pixels of each
    leave the other's view) and the prior's decode with the true K, as tracking asks for it."""
    seq = make_sequence("loop", n_frames=80, width=160, height=120, seed=0)
    prior = TwoViewPrior(seq.K, (160, 120), TwoViewPriorConfig(third_view=False))
    f, k = seq[5], seq[0]
    p = prior.pair(f, k)
    assert prior.last_status == "ok"
    return seq, f, k, p


def _scale(depth: np.ndarray, K: np.ndarray, X: np.ndarray, mask: np.ndarray) -> float:
    """Median ratio of true to estimated distances from the camera over ``mask``."""
    return float(
        np.median(
            (np.linalg.norm(backproject(depth, K), axis=-1) / np.linalg.norm(X, axis=-1))[mask]
        )
    )


def test_triangulated_pixels_of_both_images_share_one_scale(loop_pair):
    seq, f, k, p = loop_pair
    K = seq.K
    # The keyframe's true points in the frame's camera (X_ji is in camera i = the frame).
    T_fk = sim3.mul(sim3.inv(f.T_WC), k.T_WC)
    X_true_ji = sim3.act(T_fk, backproject(k.depth, K).reshape(-1, 3)).reshape(120, 160, 3)
    s_f = _scale(f.depth, K, p.X_ii, p.C_ii > 1)
    s_k = float(
        np.median(
            (np.linalg.norm(X_true_ji, axis=-1) / np.linalg.norm(p.X_ji, axis=-1))[p.C_ji > 1]
        )
    )
    assert abs(s_f / s_k - 1) < PAIR_SCALE_REL


def test_twoview_config_keeps_untriangulated_pixels_out_of_the_pose_solves(loop_pair):
    _, _, _, p = loop_pair
    filled_f, filled_k = p.C_ii.reshape(-1) == 1, p.C_ji.reshape(-1) == 1
    assert filled_f.any() and filled_k.any()  # the pair has pixels the prior filled in
    cfg = load_config("twoview")
    for section in (cfg.tracking(), cfg.backend()):
        assert section.C_conf >= 1.0
    n = filled_f.size
    idx_f2k = np.arange(n)  # identity matches: each pixel's own confidence decides
    C_f = np.asarray(
        fusion.average_confidence(
            fusion.init_pointmap(p.X_ii.reshape(-1, 3), p.C_ii.reshape(-1), cfg.fusion())
        )
    ).reshape(-1)
    C_k = p.C_ji.reshape(-1)
    Q = np.full(n, 10.0)
    valid_opt, _ = tracking.tracking_masks(np.ones(n, bool), C_f[idx_f2k], C_k, Q, cfg.tracking())
    assert not valid_opt[filled_f | filled_k].any()
    assert valid_opt[~(filled_f | filled_k)].all()


def test_a_frame_without_confident_pixels_is_tracked_not_lost():
    """With ``tracking.C_conf = 1`` and a prior that triangulated nothing (``C = 1`` everywhere),
    tracking falls back to every matched pixel instead of losing each frame."""
    import dataclasses

    from mslam.kernels import load_kernels
    from mslam.system import open_source
    from mslam.system.frontend import SlamSystem

    cfg = load_config(None, ["tracking.C_conf=1.0"])
    src = open_source("synthetic:loop:24:64x48", cfg)
    prior, pair, mono = src.prior, src.prior.pair, src.prior.mono

    def pair_floor(fi, fj):
        p = pair(fi, fj)
        return dataclasses.replace(p, C_ii=np.ones_like(p.C_ii), C_ji=np.ones_like(p.C_ji))

    prior.pair = pair_floor
    prior.mono = lambda f: (mono(f)[0], np.ones(f.shape))
    system = SlamSystem(prior, cfg, load_kernels("ref"), src.K)
    statuses = [system.process(src.sequence[i]) for i in range(10)]
    assert statuses[0] == "keyframe"
    assert set(statuses[1:]) <= {"tracked", "keyframe"} and "tracked" in statuses
