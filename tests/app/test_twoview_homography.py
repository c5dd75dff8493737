"""The homography test of the two-view prior: rotation or parallax, for any focal length.

Exact correspondences of a 70° camera (the synthetic renderer's), analysed through the 60°
focal-length guess of an uncalibrated run (``focal_guess_intrinsics``):

* a pure rotation is not a rotation of ``K⁻¹ H K`` for the guess (its plane term is over the
  margin), and is one for the focal length the focal-free test finds, close to the camera's;
  the rotation read from H at that focal length is the camera's;
* a plane seen from two centres (sideways, and head-on) and a scene in depth keep their
  parallax under the focal-free test.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from tolerances import HOMOGRAPHY_FOCAL_REL

from mslam.priors.twoview_geometry import focal_guess_intrinsics
from mslam.priors.twoview_homography import homography_fit, homography_rotation
from mslam_ref import so3
from mslam_ref.pointmap import intrinsics_from_fov

W, H = 160, 120
K_TRUE = intrinsics_from_fov(W, H, 70.0)
K_GUESS = focal_guess_intrinsics(W, H)
MIN_PARALLAX_PX = 1.0  # the prior's default min_parallax_px


def _project(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (X[:, :2] / X[:, 2:]) * K[[0, 1], [0, 1]] + K[:2, 2]


def _grid_rays(K: np.ndarray) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(5, W - 6, 24), np.linspace(5, H - 6, 18))
    uv = np.stack([u.ravel(), v.ravel()], -1)
    return np.hstack([(uv - K[:2, 2]) / K[[0, 1], [0, 1]], np.ones((len(uv), 1))])


def _pair(R: np.ndarray, t: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of points at ``depth`` along the grid's rays in camera i, and in camera j
    (``X_j = R X_i + t``), both through the true camera."""
    X_i = _grid_rays(K_TRUE) * depth[:, None]
    X_j = X_i @ R.T + t
    return _project(X_i, K_TRUE), _project(X_j, K_TRUE)


def _depths(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(1.5, 4.0, n)


@settings(max_examples=20, deadline=None)
@given(
    heading=st.floats(0.0, 2 * np.pi),
    roll=st.floats(-0.5, 0.5),
    deg=st.floats(1.5, 6.0),
)
def test_a_pure_rotation_is_one_for_some_focal_length(heading, roll, deg) -> None:
    """A turn about an axis off the optical axis (which alone fixes no focal length)."""
    axis = np.array([np.cos(heading), np.sin(heading), roll])
    R = so3.to_matrix(so3.exp(np.radians(deg) * axis / np.linalg.norm(axis)))
    uv_i, uv_j = _pair(R, np.zeros(3), _depths(np.random.default_rng(0), 24 * 18))
    free = homography_fit(uv_i, uv_j, K_GUESS, focal_free=True)
    assert free.parallax_px < MIN_PARALLAX_PX
    assert abs(free.focal_px / K_TRUE[0, 0] - 1) < HOMOGRAPHY_FOCAL_REL
    R_h = homography_rotation(free.H, K_GUESS, free.focal_px)
    assert np.degrees(np.linalg.norm(so3.log(so3.from_matrix(R_h.T @ R)))) < 0.05 * deg


def test_a_roll_is_read_at_any_focal_length() -> None:
    R = so3.to_matrix(so3.exp(np.radians([0.0, 0.0, 4.0])))  # about the optical axis
    uv_i, uv_j = _pair(R, np.zeros(3), _depths(np.random.default_rng(3), 24 * 18))
    free = homography_fit(uv_i, uv_j, K_GUESS, focal_free=True)
    assert free.parallax_px < MIN_PARALLAX_PX
    R_h = homography_rotation(free.H, K_GUESS, free.focal_px)
    assert np.degrees(np.linalg.norm(so3.log(so3.from_matrix(R_h.T @ R)))) < 0.01


def test_the_focal_guess_makes_a_rotation_look_like_parallax() -> None:
    R = so3.to_matrix(so3.exp(np.radians([0.0, 5.0, 0.0])))  # a 5° pan
    uv_i, uv_j = _pair(R, np.zeros(3), _depths(np.random.default_rng(1), 24 * 18))
    guess = homography_fit(uv_i, uv_j, K_GUESS)
    free = homography_fit(uv_i, uv_j, K_GUESS, focal_free=True)
    assert guess.parallax_px > MIN_PARALLAX_PX > free.parallax_px


def test_a_plane_or_a_scene_in_depth_keeps_its_parallax() -> None:
    rng = np.random.default_rng(2)
    R = so3.to_matrix(so3.exp(np.radians([0.5, 1.0, 0.0])))
    n = 24 * 18
    wall = np.full(n, 2.0) / _grid_rays(K_TRUE)[:, 2]  # depth along z is 2 m: a fronto wall
    cases = {
        "wall, sideways": (np.array([0.08, 0.0, 0.0]), wall),
        "wall, head-on": (np.array([0.0, 0.0, 0.15]), wall),
        "depth, sideways": (np.array([0.08, 0.0, 0.0]), _depths(rng, n)),
    }
    for name, (t, depth) in cases.items():
        uv_i, uv_j = _pair(R, t, depth)
        assert homography_fit(uv_i, uv_j, K_GUESS, focal_free=True).parallax_px > MIN_PARALLAX_PX, (
            name
        )
