"""``mslam.priors.keypoints.ratio_matches``: the BLAS ratio test gives OpenCV's matches."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mslam.priors.keypoints import ratio_matches


def _opencv(d_q, d_t, ratio, norm):
    knn = cv2.BFMatcher(norm).knnMatch(d_q, d_t, k=2)
    return {(m[0].queryIdx, m[0].trainIdx) for m in knn
            if len(m) == 2 and m[0].distance < ratio * m[1].distance}  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_float_descriptors_match_like_opencv(seed: int) -> None:
    rng = np.random.default_rng(seed)
    d_t = rng.random((300, 128)).astype(np.float32) * 100
    # half the queries are noisy copies of targets (clear matches), half are unrelated
    d_q = np.concatenate([d_t[rng.permutation(300)[:150]] + rng.normal(0, 3, (150, 128)),
                          rng.random((150, 128)) * 100]).astype(np.float32)  # fmt: skip
    q, t = ratio_matches(d_q, d_t, 0.8)
    assert q.dtype == t.dtype == np.int64
    got = set(zip(q.tolist(), t.tolist()))
    assert got == _opencv(d_q, d_t, 0.8, cv2.NORM_L2)
    assert len(got) >= 140  # the noisy copies


def test_binary_descriptors_and_degenerate_inputs() -> None:
    rng = np.random.default_rng(3)
    d_t = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    d_q = d_t[:100].copy()
    d_q[:, 0] ^= 1  # one bit off
    q, t = ratio_matches(d_q, d_t, 0.8)
    assert set(zip(q.tolist(), t.tolist())) == _opencv(d_q, d_t, 0.8, cv2.NORM_HAMMING)
    assert (q == t).all() and len(q) == 100
    for a, b in ((d_q[:0], d_t), (d_q, d_t[:1])):
        q, t = ratio_matches(a, b, 0.8)
        assert len(q) == len(t) == 0
