"""The parallax cut-off and the pointmap of a frame posed by rotation (``mslam.system.parallax``).

A pair is without parallax when its median triangulation angle, as pixels of parallax through
the focal length of its pointmap, is below ``tracking.min_pair_parallax_px``: the same number
of pixels at every image size. A frame posed by rotation alone takes its keyframe's points,
seen through its own rays, when it becomes a keyframe.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from tolerances import FOCAL_FROM_POINTMAP_RTOL, ROTATED_POINTMAP_REL

from mslam.config import load_config
from mslam.priors.base import NO_INFO_C, PairPrediction
from mslam.system.map_scale import pinhole_fit
from mslam.system.parallax import (
    MIN_PAIR_PARALLAX_PX,
    ParallaxSteps,
    parallax_px,
    rotated_pointmap,
)
from mslam_ref import so3
from mslam_ref.pointmap import backproject, intrinsics_from_fov

SIZES = [(160, 120), (640, 480)]


def _pair(K: np.ndarray, H: int, W: int) -> PairPrediction:
    X = backproject(np.ones((H, W)), K)
    C, D, Q = np.ones((H, W)), np.ones((H, W, 1)), np.ones((H, W))
    return PairPrediction(X, C, D, Q, X.copy(), C.copy(), D, Q)


def _status(angle_deg: float, p: PairPrediction) -> str:
    """``ParallaxSteps.pair_status`` for a prior that accepted the pair at this angle."""
    prior = SimpleNamespace(last_status="ok", last_info={"angle_deg": angle_deg})
    steps = SimpleNamespace(prior=prior, cfg=load_config("twoview"))
    return str(ParallaxSteps.pair_status(steps, p))  # the method reads only prior and cfg


@pytest.mark.parametrize(("W", "H"), SIZES)
def test_pinhole_fit_of_a_backprojected_pointmap_is_its_intrinsics(W: int, H: int) -> None:
    K = intrinsics_from_fov(W, H, 60.0)
    depth = 1.0 + np.random.default_rng(0).random((H, W))
    fx, fy, cx, cy = pinhole_fit(backproject(depth, K))
    np.testing.assert_allclose(
        [fx, fy, cx, cy], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], rtol=FOCAL_FROM_POINTMAP_RTOL
    )


@pytest.mark.parametrize(("W", "H"), SIZES)
def test_cutoff_is_the_same_number_of_pixels_at_every_size(W: int, H: int) -> None:
    K = intrinsics_from_fov(W, H, 60.0)
    p = _pair(K, H, W)
    f = K[0, 0]
    below = float(np.degrees(0.5 * MIN_PAIR_PARALLAX_PX / f))  # half the cut-off, in pixels
    above = float(np.degrees(2.0 * MIN_PAIR_PARALLAX_PX / f))
    assert _status(below, p) == "parallax"
    assert _status(above, p) == "ok"
    np.testing.assert_allclose(parallax_px(above, p.X_ii), 2.0 * MIN_PAIR_PARALLAX_PX,
                               rtol=FOCAL_FROM_POINTMAP_RTOL)  # fmt: skip


def test_one_angle_is_below_the_cutoff_small_and_above_it_large() -> None:
    """0.1° is ~0.24 px at 160x120 and ~0.97 px at 640x480 (60° view)."""
    small, large = [_pair(intrinsics_from_fov(W, H, 60.0), H, W) for W, H in SIZES]
    assert _status(0.1, small) == "parallax"
    assert _status(0.1, large) == "ok"


def _surface(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Depth of a smooth relief seen by the keyframe, at (sub)pixel (u, v)."""
    return 2.0 + 0.5 * np.sin(u / 9.0) + 0.3 * np.cos(v / 7.0)


def test_a_frame_rotated_about_its_keyframes_centre_gets_the_keyframes_points() -> None:
    W, H = 96, 72
    K = intrinsics_from_fov(W, H, 60.0)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    X_k = backproject(_surface(u, v), K)
    C_k = 1.0 + u / W
    R_kf = so3.to_matrix(so3.exp(np.radians([2.0, 8.0, 1.0])))  # X_k = R_kf X_f
    X_f = backproject(np.full((H, W), 0.3), K)  # the frame's rays, with depths of noise
    X, C = rotated_pointmap(X_k, C_k, R_kf, X_f)
    inside = C != NO_INFO_C  # 8° about y turns part of the view out of the keyframe's
    assert inside.any() and not inside.all()
    assert np.all((C[inside] >= C_k.min()) & (C[inside] <= C_k.max()))  # the keyframe's
    # The truth: where the frame's ray meets the relief, in the keyframe's camera.
    d = X_f @ R_kf.T
    uv = d @ K.T
    z = _surface(uv[..., 0] / uv[..., 2], uv[..., 1] / uv[..., 2])
    P_true = d * (z / d[..., 2])[..., None]
    err = np.linalg.norm(X @ R_kf.T - P_true, axis=-1) / np.linalg.norm(P_true, axis=-1)
    assert np.max(err[inside]) < ROTATED_POINTMAP_REL, np.max(err[inside])
    # Outside the keyframe: on the frame's ray, at the keyframe's median distance.
    cos = np.einsum("hwc,hwc->hw", X, X_f) / (
        np.linalg.norm(X, axis=-1) * np.linalg.norm(X_f, axis=-1)
    )
    np.testing.assert_allclose(cos[~inside], 1.0, rtol=FOCAL_FROM_POINTMAP_RTOL)
