"""What keeps the RGB-D prior cheap at 512x384, and that it computes what it says.

* separable patch descriptors: a block-structured, rank-1-per-filter, zero-sum projection,
  still unit, smooth, discriminative and invariant to brightness and contrast;
* ``C_ji``'s consistency check (``rgbd_pose.consistency``) written out equals the one through
  ``pointmap.project``;
* depth filling takes (nearly) the nearest valid pixel;
* keypoints and descriptors found on a worker thread give the same predictions as in line.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from tolerances import DESCRIPTOR_CONTRAST, F32_UNIT, F64_IDENTITY

from mslam.datasets.synthetic import make_sequence
from mslam.priors import DESC_DIM
from mslam.priors.descriptors import DescriptorConfig, _projection, patch_descriptors
from mslam.priors.rgbd import RGBDPrior, fill_depth
from mslam.priors.rgbd_pose import consistency
from mslam_ref.pointmap import project

SEP = DescriptorConfig(kind="separable")


def test_separable_projection_structure() -> None:
    p, K = SEP.patch, SEP.dim // 3
    P = _projection(SEP).reshape(p, p, 3, K, 3)  # (dy, dx, colour in, filter, colour out)
    for c in range(3):
        for d in range(3):
            block = P[:, :, c, :, d]
            if c != d:
                assert not block.any()  # a filter sees one colour channel
            else:
                np.testing.assert_array_equal(block, P[:, :, 0, :, 0])  # the same on each
    for k in range(K):
        assert np.linalg.matrix_rank(P[:, :, 0, k, 0]) == 1  # separable: g_k ⊗ h_k
    # Each filter sums to zero (so the patch mean drops out), alternately along x and y.
    np.testing.assert_allclose(P.sum(axis=(0, 1, 2)), 0.0, atol=F64_IDENTITY)
    np.testing.assert_allclose(P[:, :, 0, 0::2, 0].sum(axis=1), 0.0, atol=F64_IDENTITY)
    np.testing.assert_allclose(P[:, :, 0, 1::2, 0].sum(axis=0), 0.0, atol=F64_IDENTITY)
    with pytest.raises(ValueError, match="multiple of 3"):
        DescriptorConfig(kind="separable", dim=25)
    with pytest.raises(ValueError, match="kind"):
        DescriptorConfig(kind="sparse")


def test_separable_descriptors_discriminate_and_ignore_brightness() -> None:
    seq = make_sequence("forward", n_frames=2, width=96, height=72, seed=1)
    rgb = seq[0].rgb
    D, _ = patch_descriptors(rgb, SEP)
    assert D.shape == (72, 96, DESC_DIM) and D.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(D, axis=-1), 1.0, atol=F32_UNIT)
    near = (D[:, 1:] * D[:, :-1]).sum(-1).mean()
    rng = np.random.default_rng(0)
    far = (D.reshape(-1, DESC_DIM) * rng.permutation(D.reshape(-1, DESC_DIM))).sum(-1).mean()
    assert near > far + 0.3
    # 2·I + 1 (exact in uint8 for I <= 127): same descriptors, twice the contrast.
    half = rgb // 2
    D1, c1 = patch_descriptors(half, SEP)
    D2, c2 = patch_descriptors(2 * half + 1, SEP)
    textured = c1 > 0.01
    np.testing.assert_allclose(D2[textured], D1[textured], atol=DESCRIPTOR_CONTRAST)
    np.testing.assert_allclose(c2, 2 * c1, atol=F32_UNIT)
    flat = patch_descriptors(np.full((8, 8, 3), 120, np.uint8), SEP)[0]
    np.testing.assert_allclose(np.linalg.norm(flat, axis=-1), 1.0, atol=F32_UNIT)


def _consistency_through_project(prior, X_ji, C_jj, frame_i, valid_i):
    """The check as first written, with ``pointmap.project`` on the whole map."""
    cfg = prior.cfg
    uv, z = project(X_ji, prior.K_for(frame_i))
    H, W = frame_i.shape
    u, v = np.round(uv[..., 0]), np.round(uv[..., 1])
    inside = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    ui = np.clip(u, 0, W - 1).astype(np.int64)
    vi = np.clip(v, 0, H - 1).astype(np.int64)
    zi = frame_i.depth[vi, ui]
    bad = inside & valid_i[vi, ui] & (np.abs(zi - z) > cfg.consistency_tol * np.maximum(zi, 1e-6))
    C = np.where(bad, 1.0 + (C_jj - 1.0) * cfg.inconsistent_factor, C_jj)
    return np.where(inside, C, 1.0 + (C - 1.0) * cfg.covis_factor)


def test_consistency_equals_the_projection_formula() -> None:
    seq = make_sequence("forward", n_frames=20, width=80, height=60, seed=2)
    prior = RGBDPrior(seq)
    fi, fj = seq[5], seq[12]
    _, _, valid_i = prior._view(fi)
    X_jj, C_jj, _ = prior._view(fj)
    X = X_jj + np.array([0.3, -0.1, 0.05])  # some points leave image i
    X[:5, :5, 2] = -1.0  # behind camera i
    X[10, 10, 2] = 0.0
    got = consistency(X, C_jj, fi.depth, valid_i, prior.K_for(fi), prior.cfg)
    want = _consistency_through_project(prior, X, C_jj, fi, valid_i)
    np.testing.assert_array_equal(got, want)
    assert (got < C_jj).any() and (got == C_jj).any()  # both cases occur


def test_fill_depth_takes_a_nearest_valid_pixel() -> None:
    rng = np.random.default_rng(4)
    depth = rng.uniform(0.5, 4.0, (60, 80))  # distinct values: each names its pixel
    depth[rng.random((60, 80)) < 0.3] = 0.0
    depth[20:35, 30:60] = 0.0  # a large hole
    filled, valid = fill_depth(depth)
    assert np.array_equal(valid, depth > 0) and np.array_equal(filled[valid], depth[valid])
    exact = ndimage.distance_transform_edt(~valid)
    where = {v: (y, x) for (y, x), v in np.ndenumerate(depth) if v > 0}
    for y, x in zip(*np.nonzero(~valid)):
        sy, sx = where[filled[y, x]]
        # OpenCV's 5x5-mask distance is within 2 % of the Euclidean one.
        assert np.hypot(sy - y, sx - x) <= 1.02 * exact[y, x] + 1e-9


def test_pair_is_the_same_with_work_done_alongside(monkeypatch) -> None:
    seq = make_sequence("forward", n_frames=20, width=160, height=120, seed=0)
    threaded = RGBDPrior(seq)
    inline = RGBDPrior(seq)

    def in_line(jobs):  # compute_alongside, run in the caller's thread at once
        for key, fn in jobs.items():
            inline.cache.get(key, fn)
        return lambda *keys: None

    monkeypatch.setattr(inline.cache, "compute_alongside", in_line)
    for i, j in ((10, 13), (13, 16), (10, 16)):
        a, b = threaded.pair(seq[i], seq[j]), inline.pair(seq[i], seq[j])
        assert threaded.last_inliers == inline.last_inliers >= 15
        for name in ("X_ii", "C_ii", "D_ii", "Q_ii", "X_ji", "C_ji", "D_ji", "Q_ji"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
