"""SE(3) helpers (g2o order [omega, upsilon], left update): round trips and FD Jacobians."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from tolerances import F64_IDENTITY, F64_SOLVE, FD_SMOOTH

from mslam_ref import se3, so3

vec6 = arrays(np.float64, 6, elements=st.floats(-2.0, 2.0))
vec3 = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0))


@given(vec6)
def test_exp_log_round_trip(xi: np.ndarray) -> None:
    if np.linalg.norm(xi[:3]) > 3.0:
        xi = xi.copy()
        xi[:3] *= 3.0 / np.linalg.norm(xi[:3])
    np.testing.assert_allclose(se3.log(se3.exp(xi)), xi, atol=F64_SOLVE)


@given(vec6, vec6, vec3)
def test_mul_inv_act_matrix(a: np.ndarray, b: np.ndarray, X: np.ndarray) -> None:
    A, B = se3.exp(a), se3.exp(b)
    np.testing.assert_allclose(
        se3.to_matrix(se3.mul(A, B)), se3.to_matrix(A) @ se3.to_matrix(B), atol=F64_IDENTITY
    )
    np.testing.assert_allclose(se3.act(se3.mul(se3.inv(A), A), X), X, atol=F64_IDENTITY)
    np.testing.assert_allclose(se3.from_matrix(se3.to_matrix(A)), A, atol=F64_IDENTITY)
    np.testing.assert_allclose(
        se3.act(A, X), (se3.to_matrix(A) @ np.r_[X, 1.0])[:3], atol=F64_IDENTITY
    )


def test_exp_matches_matrix_exponential() -> None:
    from scipy.linalg import expm

    rng = np.random.default_rng(1)
    for xi in [rng.normal(size=6), np.r_[1e-7, -2e-7, 3e-8, 0.4, 0.1, -0.2], np.zeros(6)]:
        X = np.zeros((4, 4))
        X[:3, :3] = so3.hat(xi[:3])
        X[:3, 3] = xi[3:]
        np.testing.assert_allclose(se3.to_matrix(se3.exp(xi)), expm(X), atol=F64_IDENTITY)


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2), (0,)])
def test_batch_shapes(shape: tuple[int, ...]) -> None:
    xi = np.random.default_rng(0).normal(size=(*shape, 6))
    assert se3.exp(xi).shape == (*shape, 7)
    assert se3.log(se3.exp(xi)).shape == (*shape, 6)
    assert se3.to_matrix(se3.exp(xi)).shape == (*shape, 4, 4)


def test_act_jacobian_fd() -> None:
    rng = np.random.default_rng(2)
    T, X = se3.exp(rng.normal(size=6)), rng.normal(size=3)
    Y, J_xi, J_X = se3.act_and_jacobian(T, X)
    h = 1e-6
    num = np.stack(
        [(se3.act(se3.retract(T, h * e), X) - se3.act(se3.retract(T, -h * e), X)) / (2 * h)
         for e in np.eye(6)], -1)  # fmt: skip
    np.testing.assert_allclose(J_xi, num, atol=FD_SMOOTH)
    numX = np.stack(
        [(se3.act(T, X + h * e) - se3.act(T, X - h * e)) / (2 * h) for e in np.eye(3)], -1
    )
    np.testing.assert_allclose(J_X, numX, atol=FD_SMOOTH)
    np.testing.assert_allclose(Y, se3.act(T, X))


def test_validation_errors() -> None:
    with pytest.raises(ValueError, match="xi"):
        se3.exp(np.zeros(5))
    with pytest.raises(ValueError, match="T"):
        se3.act(np.zeros(7), np.zeros(3))  # zero quaternion
    with pytest.raises(ValueError, match="M"):
        se3.from_matrix(np.eye(3))
