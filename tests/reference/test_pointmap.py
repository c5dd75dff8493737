"""Pixels, rays, back-projection, resize/crop, intrinsics changes, undistortion (mslam_ref.pointmap)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from tolerances import F32_UNIT, F64_SOLVE

from mslam.datasets.images import optimal_intrinsics, resize_img, undistort, undistort_maps
from mslam_ref.pointmap import (
    backproject,
    camera_rays,
    intrinsics_after_resize,
    network_input,
    normalize_rays,
    pixel_grid,
    project,
    scale_intrinsics,
)

K = np.array([[50.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])


def test_pixel_grid_and_rays() -> None:
    g = pixel_grid(3, 4)
    assert g.shape == (3, 4, 2) and tuple(g[2, 3]) == (3.0, 2.0)
    r = camera_rays(K, 48, 64)
    np.testing.assert_allclose(r[23, 31], [-0.5 / 50, -0.5 / 52, 1.0])
    np.testing.assert_array_equal(r[..., 2], 1.0)


@given(st.floats(0.1, 10.0), st.integers(0, 63), st.integers(0, 47))
def test_backproject_project_round_trip(z: float, u: int, v: int) -> None:
    depth = np.full((48, 64), z)
    X = backproject(depth, K)
    np.testing.assert_allclose(X[v, u], z * np.array([(u - 31.5) / 50, (v - 23.5) / 52, 1.0]))
    uv, zz = project(X[v, u], K)
    np.testing.assert_allclose(uv, [u, v], atol=F64_SOLVE)
    assert zz == pytest.approx(z)


@pytest.mark.parametrize("batch", [(), (1,), (3, 1, 2), (0,)])
def test_project_and_normalize_batches(batch) -> None:
    X = np.random.default_rng(0).normal(size=(*batch, 3)) + np.array([0, 0, 3.0])
    uv, z = project(X, K)
    assert uv.shape == (*batch, 2) and z.shape == batch
    n = normalize_rays(X)
    assert n.shape == X.shape
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)
    np.testing.assert_array_equal(normalize_rays(np.zeros(3)), [0, 0, 1.0])


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="K"):
        camera_rays(np.eye(2), 4, 4)
    with pytest.raises(ValueError, match="depth"):
        backproject(np.ones(5), K)
    with pytest.raises(ValueError, match="size"):
        resize_img(np.zeros((8, 8, 3), np.uint8), 300)
    with pytest.raises(ValueError, match="img"):
        network_input(np.zeros((8, 8)))


def test_scale_intrinsics_half_pixel_rule() -> None:
    K2 = scale_intrinsics(K, (64, 48), (32, 24))
    np.testing.assert_allclose(K2[0], [25.0, 0, (31.5 + 0.5) / 2 - 0.5])
    K3 = scale_intrinsics(K, (64, 48), (32, 24), half_pixel=False)
    np.testing.assert_allclose(K3[:2, 2], [31.5 / 2, 23.5 / 2])
    # The image centre maps to the image centre under the half-pixel rule.
    Kc = np.array([[1.0, 0, 319.5], [0, 1.0, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(scale_intrinsics(Kc, (640, 480), (160, 120))[:2, 2], [79.5, 59.5])


@pytest.mark.parametrize(
    ("size_in", "size", "size_out"),
    [((640, 480), 512, (512, 384)), ((752, 480), 512, (512, 320)), ((1920, 1080), 512, (512, 288)),
     ((640, 480), 224, (224, 224)), ((512, 512), 512, (512, 384))],
)  # fmt: skip
def test_resize_img_matches_upstream_sizes(size_in, size, size_out) -> None:
    img = np.zeros((size_in[1], size_in[0], 3), np.uint8)
    out, _ = resize_img(img, size)
    assert (out.shape[1], out.shape[0]) == size_out
    assert out.shape[0] % 16 == 0 and out.shape[1] % 16 == 0


def test_intrinsics_after_resize_tracks_a_point() -> None:
    """A bright dot at a known pixel lands where the new K projects it (within a pixel)."""
    W1, H1 = 752, 480
    K1 = np.array([[400.0, 0, 370.0], [0, 400.0, 250.0], [0, 0, 1]])
    X = np.array([0.3, -0.2, 2.0])
    (u, v), _ = project(X, K1)
    img = np.zeros((H1, W1, 3), np.uint8)
    cv2.circle(img, (round(u), round(v)), 6, (255, 255, 255), -1)
    out, tr = resize_img(img, 512)
    K2 = intrinsics_after_resize(K1, tr)
    (u2, v2), _ = project(X, K2)
    ys, xs = np.nonzero(out[..., 0] > 128)
    assert abs(xs.mean() - u2) < 1.0 and abs(ys.mean() - v2) < 1.0
    assert tr[2] == pytest.approx((round(752 * 512 / 752) - 512) / 2)


def test_undistortion_recentres_principal_point() -> None:
    W, H = 64, 48
    dist = np.array([0.1, -0.05, 0.001, 0.0])
    K_opt = optimal_intrinsics(K, dist, W, H, center=True)
    np.testing.assert_allclose(K_opt[:2, 2], [(W - 1) / 2, (H - 1) / 2])
    assert K_opt[0, 0] / K_opt[1, 1] == pytest.approx(K[0, 0] / K[1, 1])
    maps = undistort_maps(K, dist, K_opt, W, H)
    img = (np.arange(W * H * 3) % 251).astype(np.uint8).reshape(H, W, 3)
    out = undistort(img, maps)
    assert out.shape == img.shape and out.dtype == np.uint8
    # Zero distortion and K_opt = K: the remap is the identity.
    ident = undistort(img, undistort_maps(K, np.zeros(4), K, W, H))
    np.testing.assert_array_equal(ident, img)
    with pytest.raises(ValueError, match="maps"):
        undistort(img[:10], maps)


def test_network_input_range() -> None:
    img = np.array([[[0, 128, 255]]], np.uint8)
    x = network_input(img)
    assert x.shape == (1, 3, 1, 1) and x.dtype == np.float32
    np.testing.assert_allclose(x.ravel(), [-1.0, 128 / 255 * 2 - 1, 1.0], atol=F32_UNIT)
