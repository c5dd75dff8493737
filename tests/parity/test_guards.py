"""Library guards: the reference and the fast twin refuse the same bad inputs with the
same message (boolean or empty arrays, Sim(3) tangents whose scale overflows, BA points at a
camera centre) and convert integer pointmaps identically."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_IDENTITY

import mslam_fast.matching as FM
import mslam_fast.sim3 as FS
from mslam_ref import matching as RM
from mslam_ref import sim3 as RS

H, W = 6, 8


def _same_error(calls) -> str:
    messages = []
    for call in calls:
        with pytest.raises(ValueError) as info:
            call()
        messages.append(str(info.value))
    assert len(set(messages)) == 1, messages
    return messages[0]


def _pointmaps(dtype=np.float64):
    rng = np.random.default_rng(3)
    X1 = rng.integers(1, 50, (H, W, 3)).astype(dtype)
    X2 = X1.copy()
    D = rng.normal(size=(H, W, 4))
    return X1, X2, D / np.linalg.norm(D, axis=-1, keepdims=True)


def test_boolean_pointmaps_rejected_by_both(fast64):
    X1, _, D = _pointmaps()
    Xb = X1 > 10
    msg = _same_error([lambda m=m: m.match(Xb, Xb, D, D) for m in (RM, FM)])
    assert "X11" in msg and "bool" in msg


def test_zero_length_descriptors_rejected_by_both(fast64):
    X1, X2, _ = _pointmaps()
    D0 = np.zeros((H, W, 0))
    msg = _same_error([lambda m=m: m.match(X1, X2, D0, D0) for m in (RM, FM)])
    assert "D11" in msg and "zero-length" in msg


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.int64])
def test_integer_pointmaps_match_like_float(fast64, dtype):
    X1, X2, D = _pointmaps(dtype)
    want = RM.match(X1.astype(np.float64), X2.astype(np.float64), D, D)
    for got in (RM.match(X1, X2, D, D), FM.match(X1, X2, D, D)):
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)


def test_boolean_prediction_rejected():
    from mslam.priors.base import PairPrediction

    X = np.ones((H, W, 3))
    C = np.ones((H, W))
    D = np.ones((H, W, 1))
    with pytest.raises(ValueError, match="X_ii: expected a numeric array"):
        PairPrediction(X > 0, C, D, C, X, C, D, C)
    with pytest.raises(ValueError, match="F >= 1"):
        PairPrediction(X, C, D[..., :0], C, X, C, D[..., :0], C)


@pytest.mark.parametrize("sigma", [690.0, 699.0, 710.0, 1e4, -710.0, np.float64(-800)])
def test_sim3_exp_with_huge_sigma_same_error(fast64, sigma):
    xi = np.array([0.1, 0.0, 0.0, 0.0, 0.2, 0.0, sigma])
    T = RS.exp(np.zeros(7))
    calls = [lambda m=m: m.exp(xi) for m in (RS, FS)]
    calls += [lambda m=m: m.retract(T, xi) for m in (RS, FS)]
    assert "sigma" in _same_error(calls)


@pytest.mark.parametrize("sigma", [689.0, -689.0])
def test_sim3_exp_just_below_the_cap_is_finite_and_equal(fast64, sigma):
    xi = np.array([0.1, 0.0, 0.0, 0.0, 0.2, 0.0, sigma])
    want = RS.exp(xi)
    assert np.isfinite(want).all()
    np.testing.assert_allclose(FS.exp(xi), want, rtol=F64_IDENTITY, atol=0)


def test_sim3_exp_cap_in_float32(fast):
    xi = np.array([0.1, 0.0, 0.0, 0.0, 0.2, 0.0, 74.0 if fast == "f32" else 689.0])
    assert np.isfinite(FS.exp(xi)).all()
    with pytest.raises(ValueError, match="sigma"):
        FS.exp(xi * [1, 1, 1, 1, 1, 1, 1.05 if fast == "f32" else 1.01])


def test_ba_point_at_camera_centre_same_error(fast64):
    import mslam_fast.ba as fast_ba
    import mslam_ref.ba as ref_ba
    from mslam_ref.ba import lm, synthetic

    problem, _ = synthetic.make_bal_problem(n_cams=3, n_points=10)
    c = int(problem.obs_cam[0])
    problem.cameras[c, :3] = 0.0
    problem.points[problem.obs_pt[0]] = -problem.cameras[c, 3:6]
    cfg = lm.LMConfig(iterations=2)
    msg = _same_error([lambda k=k: lm.optimize(problem, cfg, k) for k in (ref_ba, fast_ba)])
    assert "camera centre" in msg and "observation 0" in msg
