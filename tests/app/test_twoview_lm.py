"""The two-view pose refinement's small solver (``mslam.priors.twoview_lm``) and the
cheirality counts of its hypotheses: their batched evaluations give the numbers of one
evaluation at a time, bit for bit, so a faster path never moves a trajectory."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import TWOVIEW_LM_FORMULA

import mslam.priors.twoview_lm as lm
from mslam.priors.twoview_geometry import (
    front_counts,
    refine_pose,
    sampson_residuals,
    triangulate_midpoint,
)
from mslam_ref import so3

K = np.array([[138.6, 0.0, 79.5], [0.0, 138.6, 59.5], [0.0, 0.0, 1.0]])


def _poses(rng, M: int):
    R = lm.so3_exp(rng.normal(size=(M, 3)) * 0.1)
    t = rng.normal(size=(M, 3))
    return R, t


def test_so3_exp_of_a_stack_is_each_vector_bit_for_bit_and_the_reference_map() -> None:
    rng = np.random.default_rng(0)
    w = rng.normal(size=(40, 3)) * 10.0 ** rng.uniform(-14, 0, size=(40, 1))
    w[0] = 0.0
    R = lm.so3_exp(w)
    assert R.shape == (40, 3, 3)
    for k in range(len(w)):
        assert np.array_equal(R[k], lm.so3_exp(w[k]))
        R_ref = so3.to_matrix(so3.exp(w[k]))
        np.testing.assert_allclose(R[k], R_ref, rtol=0, atol=TWOVIEW_LM_FORMULA)


@pytest.mark.parametrize("n", [7, 600, lm.ONE_PRODUCT_MAX_N, lm.ONE_PRODUCT_MAX_N + 1, 4000])
def test_sampson_of_many_poses_is_one_pose_at_a_time_bit_for_bit(n: int) -> None:
    rng = np.random.default_rng(n)
    uv_i = rng.uniform(0, 160, (n, 2))
    uv_j = uv_i + rng.normal(size=(n, 2)) * 3
    R, t = _poses(rng, 5)
    f = lm.sampson_fn(uv_i, uv_j, K)
    r = f(R, t)
    assert r.shape == (5, n) and r.flags["C_CONTIGUOUS"]
    for m in range(5):
        assert np.array_equal(r[m], f(R[m : m + 1], t[m : m + 1])[0])
        r_one = sampson_residuals(uv_i, uv_j, K, R[m], t[m])
        np.testing.assert_allclose(r[m], r_one, rtol=0, atol=TWOVIEW_LM_FORMULA)


def test_both_evaluation_paths_give_the_same_refined_pose(monkeypatch) -> None:
    """The one-product path and the per-pose path: same residuals, same solver path."""
    rng = np.random.default_rng(3)
    n = 600
    X = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(2, 4, n)])
    R_true, t_true = lm.so3_exp(np.array([0.02, -0.05, 0.01])), np.array([0.1, 0.02, 0.01])
    x_i, x_j = X @ K.T, (X @ R_true.T + t_true) @ K.T
    uv_i = x_i[:, :2] / x_i[:, 2:]
    uv_j = x_j[:, :2] / x_j[:, 2:] + rng.normal(size=(n, 2)) * 0.3
    R0 = lm.so3_exp(np.array([0.01, 0.0, -0.01])) @ R_true
    t0 = t_true + np.array([0.02, -0.01, 0.0])
    batched = refine_pose(uv_i, uv_j, K, R0, t0)
    monkeypatch.setattr(lm, "ONE_PRODUCT_MAX_N", -1)
    per_pose = refine_pose(uv_i, uv_j, K, R0, t0)
    assert np.array_equal(batched[0], per_pose[0]) and np.array_equal(batched[1], per_pose[1])
    angle = np.degrees(np.arccos(np.clip((np.trace(batched[0].T @ R_true) - 1) / 2, -1, 1)))
    assert angle < 0.2  # 0.3 px noise on 600 points: the refined rotation within 0.2°


def test_front_counts_are_the_two_signs_triangulated_one_by_one() -> None:
    """One pass gives the cheirality counts of ``t`` and ``-t`` that two triangulations give."""
    rng = np.random.default_rng(5)
    for trial in range(20):
        n = 300
        X = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(-2, 4, n)])
        R = lm.so3_exp(rng.normal(size=3) * 0.1)
        t = rng.normal(size=3) * 10.0 ** rng.uniform(-4, 0)
        x_i, x_j = X @ K.T, (X @ R.T + t) @ K.T
        uv_i = x_i[:, :2] / x_i[:, 2:] + rng.normal(size=(n, 2)) * 0.5
        uv_j = x_j[:, :2] / x_j[:, 2:] + rng.normal(size=(n, 2)) * 0.5
        if trial == 0:
            uv_j = uv_i.copy()  # parallel rays: nothing triangulates
        n_pos = int(triangulate_midpoint(uv_i, uv_j, K, R, t)[2].sum())
        n_neg = int(triangulate_midpoint(uv_i, uv_j, K, R, -t)[2].sum())
        assert front_counts(uv_i, uv_j, K, R, t) == (n_pos, n_neg)
        assert trial == 0 or n_pos + n_neg > 0
