"""Pointmap fusion (mslam_ref.fusion): every filtering mode against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_IDENTITY

from mslam_ref import fusion
from mslam_ref.fusion import FusionConfig

X1 = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 1.0], [0.0, 0.0, 3.0]])
C1 = np.array([1.0, 2.0, 3.0])
X2 = np.array([[3.0, 0.0, 4.0], [0.0, 3.0, 1.0], [1.0, 0.0, 3.0]])
C2 = np.array([3.0, 2.0, 1.0])


def _two(mode: str, score: str = "median"):
    cfg = FusionConfig(mode, score)
    s0 = fusion.init_pointmap(X1, C1, cfg)
    return cfg, s0, fusion.update_pointmap(s0, X2, C2, cfg)


def test_init() -> None:
    s = fusion.init_pointmap(X1, C1)
    assert (s.N, s.N_updates, s.score) == (1, 1, 2.0)
    np.testing.assert_array_equal(s.X_canon, X1)
    assert s.X_canon is not X1  # a copy
    assert fusion.init_pointmap(X1, C1, FusionConfig(filtering_score="mean")).score == 2.0


def test_weighted_pointmap() -> None:
    cfg, s0, s = _two("weighted_pointmap")
    expect = np.array([[2.5, 0.0, 3.5], [0.0, 2.0, 1.0], [0.25, 0.0, 3.0]])
    np.testing.assert_allclose(s.X_canon, expect)
    np.testing.assert_allclose(s.C, [4.0, 4.0, 4.0])
    assert (s.N, s.N_updates) == (2, 2)
    np.testing.assert_allclose(fusion.average_confidence(s), [2.0, 2.0, 2.0])
    np.testing.assert_array_equal(s0.X_canon, X1)  # input state untouched
    s3 = fusion.update_pointmap(s, X2, C2, cfg)
    assert (s3.N, s3.N_updates) == (3, 3)


def test_weighted_spherical() -> None:
    _, _, s = _two("weighted_spherical")
    # pixel 1: r = sqrt2 and sqrt10, phi = pi/2 both, theta = acos(1/sqrt2), acos(1/sqrt10)
    r = (2 * np.sqrt(2) + 2 * np.sqrt(10)) / 4
    th = (2 * np.arccos(1 / np.sqrt(2)) + 2 * np.arccos(1 / np.sqrt(10))) / 4
    np.testing.assert_allclose(
        s.X_canon[1], [0.0, r * np.sin(th), r * np.cos(th)], atol=F64_IDENTITY
    )
    # pixel 0: phi = 0 both, radii 5 and sqrt5 (weights 1, 3)
    r0 = (np.sqrt(5) + 3 * 5) / 4
    th0 = (np.arccos(2 / np.sqrt(5)) + 3 * np.arccos(4 / 5)) / 4
    np.testing.assert_allclose(s.X_canon[0], [r0 * np.sin(th0), 0.0, r0 * np.cos(th0)])
    assert (s.N, s.N_updates) == (2, 2)
    np.testing.assert_allclose(s.C, C1 + C2)


def test_recent() -> None:
    _, _, s = _two("recent")
    np.testing.assert_array_equal(s.X_canon, X2)
    np.testing.assert_array_equal(s.C, C2)
    assert (s.N, s.N_updates) == (1, 2)


def test_first_replaces_once() -> None:
    cfg, _, s = _two("first")
    np.testing.assert_array_equal(s.X_canon, X2)
    s3 = fusion.update_pointmap(s, X1 * 7, C1, cfg)
    np.testing.assert_array_equal(s3.X_canon, X2)
    assert (s3.N, s3.N_updates) == (1, 3)


def test_best_score() -> None:
    cfg, _, s = _two("best_score")  # median C2 = 2 is not > 2: keep
    np.testing.assert_array_equal(s.X_canon, X1)
    s3 = fusion.update_pointmap(s, X2, C2 + 0.5, cfg)  # median 2.5 > 2: replace
    np.testing.assert_array_equal(s3.X_canon, X2)
    assert (s3.score, s3.N, s3.N_updates) == (2.5, 1, 3)
    cfg_m = FusionConfig("best_score", "mean")
    s0 = fusion.init_pointmap(X1, np.array([1.0, 1.0, 10.0]), cfg_m)  # mean 4, median 1
    assert fusion.update_pointmap(s0, X2, np.full(3, 3.0), cfg_m).X_canon is s0.X_canon


def test_indep_conf() -> None:
    _, _, s = _two("indep_conf")
    np.testing.assert_array_equal(s.X_canon, np.stack([X2[0], X1[1], X1[2]]))  # 2 > 2 is false
    np.testing.assert_array_equal(s.C, [3.0, 2.0, 3.0])
    assert (s.N, s.N_updates) == (1, 2)


def test_grid_shape_is_kept_and_spherical_origin_is_finite() -> None:
    X = np.zeros((2, 3, 3))
    s = fusion.init_pointmap(X, np.ones((2, 3)), FusionConfig("weighted_spherical"))
    s2 = fusion.update_pointmap(s, X, np.ones((2, 3)), FusionConfig("weighted_spherical"))
    assert s2.X_canon.shape == (2, 3, 3) and np.all(s2.X_canon == 0)


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="filtering_mode"):
        FusionConfig("median")
    with pytest.raises(ValueError, match="filtering_score"):
        FusionConfig(filtering_score="max")
    with pytest.raises(ValueError, match="C"):
        fusion.init_pointmap(X1, C1[:2])
    with pytest.raises(ValueError, match="C"):
        fusion.init_pointmap(X1, -C1)
    s = fusion.init_pointmap(X1, C1)
    with pytest.raises(ValueError, match="X"):
        fusion.update_pointmap(s, X1[:2], C1[:2])
