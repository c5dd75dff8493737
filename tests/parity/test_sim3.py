"""``mslam_fast.sim3`` against ``mslam_ref.sim3`` on hypothesis inputs, in f64 and f32.

Tolerances come from ``tests/tolerances.py`` (rows "sim3"). Also: batch shapes including (0,),
broadcasting, inputs never mutated, float32 inputs accepted, bad input raises like the reference.
"""

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
    edge_element,
    edge_examples,
    edge_tangent,
    points,
    sim3_elements,
    stacked,
    tangents,
)
from tolerances import tol

import mslam_fast.sim3 as F
from mslam_ref import sim3 as R

#: ``fast`` is function-scoped but only (re)asserts the runtime precision: safe under @given.
fixture_ok = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture]
)
DTYPE = {"f64": np.float64, "f32": np.float32}
N = 6  # elements per hypothesis example


def check(got: np.ndarray, want: np.ndarray, fp: str) -> None:
    assert got.dtype == DTYPE[fp]
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, **tol("sim3", fp))


def edge_batch(th: float, sg: float) -> np.ndarray:
    return batch_of(edge_element(th, sg), (N,))


def edge_tangents(th: float, sg: float) -> np.ndarray:
    return batch_of(edge_tangent(th, sg), (N,))


def edge_points(th: float, sg: float) -> np.ndarray:
    return batch_of(EDGE_POINT, (N,))


@fixture_ok
@edge_examples(xi=edge_tangents)
@given(xi=stacked(tangents(), N))
def test_exp(fast: str, xi: np.ndarray) -> None:
    check(F.exp(xi), R.exp(xi), fast)


@fixture_ok
@edge_examples(T=edge_batch)
@given(T=stacked(sim3_elements(), N))
def test_log(fast: str, T: np.ndarray) -> None:
    # Near theta = pi the sign of w picks +-pi axis; rounding to f32 keeps that sign.
    check(F.log(T), R.log(T), fast)


@pytest.mark.parametrize("sigma", [240.0, 600.0, 689.0, -689.0])
@pytest.mark.parametrize("theta", [0.0, 0.5])
def test_log_near_the_sigma_cap(fast64: str, sigma: float, theta: float) -> None:
    # s = e^sigma up to 1e299 (|sigma| < 690): W's determinant (~ C^3) overflows unless scaled.
    T = R.exp(np.r_[0.3, -1.2, 2.0, theta, 0.0, 0.0, sigma])
    check(F.log(T), R.log(T), fast64)


@fixture_ok
@given(A=stacked(sim3_elements(), N), B=stacked(sim3_elements(), N))
def test_mul(fast: str, A: np.ndarray, B: np.ndarray) -> None:
    check(F.mul(A, B), R.mul(A, B), fast)


@fixture_ok
@edge_examples(T=edge_batch)
@given(T=stacked(sim3_elements(), N))
def test_inv(fast: str, T: np.ndarray) -> None:
    check(F.inv(T), R.inv(T), fast)


@fixture_ok
@edge_examples(T=edge_batch, X=edge_points)
@given(T=stacked(sim3_elements(), N), X=stacked(points(), N))
def test_act_and_jacobian(fast: str, T: np.ndarray, X: np.ndarray) -> None:
    check(F.act(T, X), R.act(T, X), fast)
    P, J = F.act_and_jacobian(T, X)
    P_ref, J_ref = R.act_and_jacobian(T, X)
    check(P, P_ref, fast)
    check(J, J_ref, fast)


@fixture_ok
@edge_examples(T=edge_batch)
@given(T=stacked(sim3_elements(), N))
def test_adjoint_and_matrices(fast: str, T: np.ndarray) -> None:
    check(F.adjoint(T), R.adjoint(T), fast)
    check(F.to_matrix(T), R.to_matrix(T), fast)


@fixture_ok
@edge_examples(T=edge_batch, J=edge_tangents)
@given(T=stacked(sim3_elements(), N), J=stacked(tangents(), N))
def test_adjoint_inv_apply(fast: str, T: np.ndarray, J: np.ndarray) -> None:
    check(F.adjoint_inv_apply(T, J), R.adjoint_inv_apply(T, J), fast)


@fixture_ok
@edge_examples(T=edge_batch, xi=edge_tangents)
@given(T=stacked(sim3_elements(), N), xi=stacked(tangents(), N))
def test_retract(fast: str, T: np.ndarray, xi: np.ndarray) -> None:
    check(F.retract(T, xi), R.retract(T, xi), fast)


# --- shapes, broadcasting, no mutation, dtypes -------------------------------------------------


def _calls(T: np.ndarray, xi: np.ndarray, X: np.ndarray) -> dict[str, Callable[[Any], Any]]:
    """Every public function of ``mslam_fast.sim3`` as ``module -> outputs``."""
    return {
        "exp": lambda m: m.exp(xi),
        "log": lambda m: m.log(T),
        "mul": lambda m: m.mul(T, T),
        "inv": lambda m: m.inv(T),
        "act": lambda m: m.act(T, X),
        "act_and_jacobian": lambda m: m.act_and_jacobian(T, X),
        "adjoint": lambda m: m.adjoint(T),
        "adjoint_inv_apply": lambda m: m.adjoint_inv_apply(T, xi),
        "retract": lambda m: m.retract(T, xi),
        "to_matrix": lambda m: m.to_matrix(T),
    }


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=str)
def test_batch_shapes_and_no_mutation(fast: str, shape: tuple[int, ...]) -> None:
    T = batch_of(edge_element(0.7, 0.2), shape)
    T[..., 3:7] *= 2.0  # unnormalised: the wrappers must normalise a copy
    xi = batch_of(edge_tangent(0.3, -0.1), shape)
    X = batch_of(EDGE_POINT, shape)
    copies = [a.copy() for a in (T, xi, X)]
    calls = _calls(T, xi, X)
    assert set(calls) == set(F.__all__)
    for name, call in calls.items():
        got, want = call(F), call(R)
        for g, w in zip(*(o if isinstance(o, tuple) else (o,) for o in (got, want)), strict=True):
            assert g.shape == w.shape, name
            assert g.dtype == DTYPE[fast], name
            if g.size:
                np.testing.assert_allclose(g, w, **tol("sim3", fast), err_msg=name)
    for a, c in zip((T, xi, X), copies, strict=True):
        np.testing.assert_array_equal(a, c)


def test_broadcasting(fast: str) -> None:
    rng = np.random.default_rng(3)
    T = R.exp(rng.normal(size=(3, 1, 7)))
    B = R.exp(rng.normal(size=(4, 7)))
    X = rng.normal(size=(1, 4, 3))
    J = rng.normal(size=(4, 7))
    check(F.act(T, X), R.act(T, X), fast)
    check(F.mul(T, B), R.mul(T, B), fast)
    check(F.adjoint_inv_apply(T, J), R.adjoint_inv_apply(T, J), fast)
    check(F.retract(T, J), R.retract(T, J), fast)
    for got, want in zip(F.act_and_jacobian(T, X), R.act_and_jacobian(T, X), strict=True):
        check(got, want, fast)


def test_float32_and_list_inputs_accepted(fast: str) -> None:
    rng = np.random.default_rng(4)
    T = R.exp(rng.normal(size=(5, 7))).astype(np.float32)
    X = rng.normal(size=(5, 3)).astype(np.float32)
    check(F.act(T, X), R.act(T, X), fast)
    xi = [*X[0].tolist(), 0.1, 0.2, 0.3, 0.4]
    check(F.exp(xi), R.exp(xi), fast)


@given(T=sim3_elements(), X=points())
@fixture_ok
def test_unnormalised_quaternion_is_normalised(fast: str, T: np.ndarray, X: np.ndarray) -> None:
    T3 = T.copy()
    T3[3:7] *= 3.0
    check(F.act(T3, X), R.act(T, X), fast)
    check(F.inv(T3), R.inv(T), fast)


# --- bad input: same ValueError as the reference -------------------------------------------------

GOOD_T = np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0, 1.5])
GOOD_XI = np.arange(1.0, 8.0) * 0.1


def _bad_T() -> list[tuple[np.ndarray | float, str]]:
    nan_T, inf_T, zero_s, neg_s, zero_q = (GOOD_T.copy() for _ in range(5))
    nan_T[0], inf_T[4], zero_s[7], neg_s[7] = np.nan, np.inf, 0.0, -2.0
    zero_q[3:7] = 0.0
    return [
        (GOOD_T[:7], "trailing shape"),
        (1.0, "trailing shape"),
        (nan_T, "non-finite"),
        (inf_T, "non-finite"),
        (zero_s, "scale"),
        (neg_s, "scale"),
        (zero_q, "zero norm"),
    ]


@pytest.mark.parametrize(("bad", "msg"), _bad_T(), ids=lambda v: v if isinstance(v, str) else "")
def test_bad_element_raises_like_reference(fast: str, bad: Any, msg: str) -> None:
    X, J = np.ones(3), GOOD_XI
    for call, name in [
        (lambda m: m.log(bad), "T"),
        (lambda m: m.inv(bad), "T"),
        (lambda m: m.act(bad, X), "T"),
        (lambda m: m.act_and_jacobian(bad, X), "T"),
        (lambda m: m.adjoint(bad), "T"),
        (lambda m: m.adjoint_inv_apply(bad, J), "T"),
        (lambda m: m.retract(bad, J), "T"),
        (lambda m: m.to_matrix(bad), "T"),
        (lambda m: m.mul(bad, GOOD_T), "A"),
        (lambda m: m.mul(GOOD_T, bad), "B"),
    ]:
        for mod in (R, F):
            with pytest.raises(ValueError, match=rf"^{name}: .*{msg}"):
                call(mod)


@pytest.mark.parametrize(
    ("call", "msg"),
    [
        (lambda m: m.exp(np.ones(6)), "^xi: .*trailing shape"),
        (lambda m: m.exp(GOOD_XI * np.nan), "^xi: .*non-finite"),
        (lambda m: m.retract(GOOD_T, np.ones(8)), "^xi: .*trailing shape"),
        (lambda m: m.adjoint_inv_apply(GOOD_T, np.full(7, np.inf)), "^J: .*non-finite"),
        (lambda m: m.act(GOOD_T, np.ones(4)), "^X: .*trailing shape"),
        (lambda m: m.act_and_jacobian(GOOD_T, [np.nan, 0, 0]), "^X: .*non-finite"),
    ],
)
def test_bad_vectors_raise_like_reference(fast: str, call: Any, msg: str) -> None:
    for mod in (R, F):
        with pytest.raises(ValueError, match=msg):
            call(mod)
