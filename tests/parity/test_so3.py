"""``mslam_fast.so3`` against ``mslam_ref.so3`` on hypothesis inputs, in f64 and f32."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from strategies import (
    BATCH_SHAPES,
    EDGE_POINT,
    batch_of,
    points,
    quaternions,
    rotation_vectors,
    stacked,
)
from tolerances import tol

import mslam_fast.so3 as F
from mslam_ref import so3 as R

fixture_ok = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture]
)
DTYPE = {"f64": np.float64, "f32": np.float32}
N = 6


def check(got: np.ndarray, want: np.ndarray, fp: str) -> None:
    assert got.dtype == DTYPE[fp]
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, **tol("so3", fp))


@fixture_ok
@given(phi=stacked(rotation_vectors(max_angle=np.pi), N))
def test_exp(fast: str, phi: np.ndarray) -> None:
    check(F.exp(phi), R.exp(phi), fast)


@fixture_ok
@given(q=stacked(quaternions(), N))
def test_log(fast: str, q: np.ndarray) -> None:
    check(F.log(q), R.log(q), fast)
    check(F.log(2.5 * q), R.log(q), fast)  # normalised inside


@fixture_ok
@given(q1=stacked(quaternions(), N), q2=stacked(quaternions(), N), X=stacked(points(), N))
def test_mul_conj_act(fast: str, q1: np.ndarray, q2: np.ndarray, X: np.ndarray) -> None:
    check(F.mul(q1, q2), R.mul(q1, q2), fast)
    check(F.conj(q1), R.conj(q1), fast)
    check(F.act(q1, X), R.act(q1, X), fast)


@fixture_ok
@given(q=stacked(quaternions(), N), v=stacked(points(), N))
def test_matrices_hat_normalize(fast: str, q: np.ndarray, v: np.ndarray) -> None:
    check(F.to_matrix(q), R.to_matrix(q), fast)
    check(F.hat(v), R.hat(v), fast)
    check(F.normalize(3.0 * q), R.normalize(3.0 * q), fast)


def _calls(q: np.ndarray, X: np.ndarray) -> dict[str, Callable[[Any], Any]]:
    return {
        "exp": lambda m: m.exp(X * 0.1),
        "log": lambda m: m.log(q),
        "mul": lambda m: m.mul(q, q),
        "conj": lambda m: m.conj(q),
        "act": lambda m: m.act(q, X),
        "to_matrix": lambda m: m.to_matrix(q),
        "hat": lambda m: m.hat(X),
        "normalize": lambda m: m.normalize(q),
    }


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=str)
def test_batch_shapes_and_no_mutation(fast: str, shape: tuple[int, ...]) -> None:
    q = batch_of(R.exp(np.array([0.3, -0.2, 0.9])), shape)
    X = batch_of(EDGE_POINT, shape)
    copies = (q.copy(), X.copy())
    calls = _calls(q, X)
    assert set(calls) == set(F.__all__)
    for name, call in calls.items():
        got, want = call(F), call(R)
        assert got.shape == want.shape, name
        assert got.dtype == DTYPE[fast], name
        np.testing.assert_allclose(got, want, **tol("so3", fast), err_msg=name)
    np.testing.assert_array_equal(q, copies[0])
    np.testing.assert_array_equal(X, copies[1])


def test_broadcasting_and_float32_inputs(fast: str) -> None:
    rng = np.random.default_rng(5)
    q = R.exp(rng.normal(size=(3, 1, 3)))
    q2 = R.exp(rng.normal(size=(4, 3))).astype(np.float32)
    X = rng.normal(size=(1, 4, 3)).astype(np.float32)
    check(F.act(q, X), R.act(q, X), fast)
    check(F.mul(q, q2), R.mul(q, q2), fast)


@pytest.mark.parametrize(
    ("call", "msg"),
    [
        (lambda m: m.exp(np.ones(4)), "^phi: .*trailing shape"),
        (lambda m: m.exp([np.nan, 0, 0]), "^phi: .*non-finite"),
        (lambda m: m.log(np.zeros(4)), "^q: .*zero norm"),
        (lambda m: m.log(np.ones(3)), "^q: .*trailing shape"),
        (lambda m: m.normalize(np.zeros((2, 4)), "quat"), "^quat: .*zero norm"),
        (lambda m: m.mul(np.ones(3), np.ones(4)), "^q1: .*trailing shape"),
        (lambda m: m.mul(np.ones(4), [0, 0, np.inf, 1]), "^q2: .*non-finite"),
        (lambda m: m.conj(np.ones(5)), "^q: .*trailing shape"),
        (lambda m: m.act(np.ones(4), np.ones(4)), "^X: .*trailing shape"),
        (lambda m: m.to_matrix(np.full(4, np.nan)), "^q: .*non-finite"),
        (lambda m: m.hat(np.ones(2)), "^v: .*trailing shape"),
    ],
)
def test_bad_input_raises_like_reference(fast: str, call: Any, msg: str) -> None:
    for mod in (R, F):
        with pytest.raises(ValueError, match=msg):
            call(mod)
