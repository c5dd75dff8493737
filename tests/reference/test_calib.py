"""Calibrated residuals and the ray constraint (mslam_ref.calib): values, validity and
Jacobians against central finite differences of the left retraction."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_IDENTITY, F64_SOLVE, FD_ATOL, FD_RTOL, FD_SMOOTH

from mslam_ref import calib, sim3
from mslam_ref.pointmap import backproject
from mslam_ref.tracking import TrackingConfig

H, W = 12, 16
K = np.array([[20.0, 0.0, 7.5], [0.0, 22.0, 5.5], [0.0, 0.0, 1.0]])


def _scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    depth = 2.0 + 0.3 * np.sin(u / 3.0) + 0.2 * np.cos(v / 2.0)
    X_k = backproject(depth, K)
    T = sim3.exp(np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.03, 3), [0.05]]))
    X_f = sim3.act(sim3.inv(T), X_k.reshape(-1, 3))
    return X_k, X_f, T


def _fd(fun, T: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central differences of fun(T) (N, c) along the 7 left-perturbation directions."""
    cols = []
    for k in range(7):
        e = np.zeros(7)
        e[k] = eps
        cols.append((fun(sim3.retract(T, e)) - fun(sim3.retract(T, -e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def test_constrain_points_to_ray() -> None:
    rng = np.random.default_rng(1)
    X = rng.normal(0, 1, (2, H, W, 3))
    X[..., 2] = rng.uniform(0.5, 3.0, (2, H, W))
    Y = calib.constrain_points_to_ray(X, K)
    assert Y.shape == X.shape
    np.testing.assert_array_equal(Y[..., 2], X[..., 2])
    uv = (Y[..., :2] / Y[..., 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    v, u = np.mgrid[0:H, 0:W]
    np.testing.assert_allclose(uv[0], np.stack([u, v], -1), atol=F64_IDENTITY)
    np.testing.assert_allclose(calib.constrain_points_to_ray(Y, K), Y)  # idempotent
    with pytest.raises(ValueError, match="X"):
        calib.constrain_points_to_ray(np.ones((4, 3)), K)
    with pytest.raises(ValueError, match="K"):
        calib.constrain_points_to_ray(X, np.zeros((3, 3)))


def test_project_calib_jacobian_and_validity() -> None:
    rng = np.random.default_rng(2)
    P = rng.normal(0, 0.5, (50, 3)) + np.array([0.0, 0.0, 2.0])
    _, J, _ = calib.project_calib_and_jacobian(P, K, (H, W))
    eps = 1e-6
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps
        fd = (
            calib.project_calib_and_jacobian(P + d, K, (H, W))[0]
            - calib.project_calib_and_jacobian(P - d, K, (H, W))[0]
        ) / (2 * eps)
        np.testing.assert_allclose(J[:, :, a], fd, atol=FD_ATOL, rtol=FD_ATOL)
    # border: strict inequalities, border = -10 admits points up to 10 px outside
    x = lambda u: (u - K[0, 2]) / K[0, 0]
    Pb = np.array(
        [
            [x(-9.99), 0, 1],
            [x(-10.0), 0, 1],
            [x(W - 1 + 9.99), 0, 1],
            [x(W - 1 + 10), 0, 1],
            [0, 0, -1],
            [0, 0, 0],
        ]
    )
    _, Jb, vb = calib.project_calib_and_jacobian(Pb, K, (H, W), border=-10)
    assert vb.tolist() == [True, False, True, False, False, False]
    pzb = calib.project_calib_and_jacobian(Pb, K, (H, W))[0]
    assert np.all(pzb[4:] == 0) and np.all(Jb[4:] == 0) and np.all(np.isfinite(pzb))
    assert not calib.project_calib_and_jacobian(Pb[:1], K, (H, W), border=0)[2][0]


def test_calib_residual_zero_at_truth_and_jacobian() -> None:
    X_k, X_f, T = _scene()
    r, J, valid = calib.calib_residual_and_jacobian(T, X_f, X_k, K, TrackingConfig())
    assert r.shape == (H * W, 3) and J.shape == (H * W, 3, 7) and valid.all()
    np.testing.assert_allclose(r, 0.0, atol=F64_SOLVE)
    T1 = sim3.retract(T, np.array([0.01, -0.02, 0.01, 0.01, 0.02, -0.01, 0.03]))
    _, J1, v1 = calib.calib_residual_and_jacobian(T1, X_f, X_k, K)
    fd = _fd(lambda TT: calib.calib_residual_and_jacobian(TT, X_f, X_k, K)[0], T1)
    np.testing.assert_allclose(J1[v1], fd[v1], atol=FD_ATOL, rtol=FD_RTOL)


def test_calib_residual_validity() -> None:
    X_k, X_f, T = _scene()
    X_k = X_k.copy()
    X_k[0, 0, 2] = 0.0  # invalid measurement
    X_f = X_f.copy()
    X_f[5] = sim3.act(sim3.inv(T), np.array([0.0, 0.0, -1.0]))  # behind the camera
    r, J, valid = calib.calib_residual_and_jacobian(T, X_f, X_k, K)
    assert not valid[0] and not valid[5] and valid.sum() == H * W - 2
    assert np.all(r[~valid] == 0) and np.all(J[~valid] == 0)
    with pytest.raises(ValueError, match="X_k"):
        calib.calib_residual_and_jacobian(T, X_f, X_k.reshape(-1, 3), K)
    with pytest.raises(ValueError, match="X_f"):
        calib.calib_residual_and_jacobian(T, X_f[:-1], X_k, K)


def test_point_residual() -> None:
    X_k, X_f, T = _scene(3)
    r, _ = calib.point_residual_and_jacobian(T, X_f, X_k)
    np.testing.assert_allclose(r, 0.0, atol=F64_IDENTITY)
    T1 = sim3.retract(T, np.full(7, 0.02))
    _, J1 = calib.point_residual_and_jacobian(T1, X_f, X_k)
    fd = _fd(lambda TT: calib.point_residual_and_jacobian(TT, X_f, X_k)[0], T1)
    np.testing.assert_allclose(J1, fd, atol=FD_SMOOTH)
