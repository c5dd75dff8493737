"""Properties of ``mslam_ref.so3``: Exp/Log, products, matrices, shapes, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given
from strategies import (
    BATCH_SHAPES,
    EDGE_CASES,
    EDGE_POINT,
    batch_of,
    edge_examples,
    points,
    quaternions,
    rotation_vectors,
    stacked,
    unit_axes,
)
from tolerances import F64_COPY, F64_IDENTITY, F64_SERIES, F64_ULPS

from mslam_ref import so3

EDGE_AXIS = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])


def edge_phi(theta: float, sigma: float = 0.0) -> np.ndarray:
    return theta * EDGE_AXIS


@edge_examples(phi=edge_phi)
@given(phi=rotation_vectors())
def test_log_exp_roundtrip(phi: np.ndarray) -> None:
    """Log(Exp(phi)) = phi for ||phi|| < pi, including tiny angles and angles near pi."""
    np.testing.assert_allclose(so3.log(so3.exp(phi)), phi, rtol=F64_SERIES, atol=F64_COPY)


@given(q=quaternions())
def test_exp_log_roundtrip_any_sign(q: np.ndarray) -> None:
    """Exp(Log(q)) = +-q, ||Log q|| <= pi, and Log(-q) = Log(q) (same rotation)."""
    phi = so3.log(q)
    assert np.linalg.norm(phi) <= np.pi + 1e-12
    back = so3.exp(phi)
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-10
    np.testing.assert_allclose(
        so3.to_matrix(so3.exp(so3.log(-q))), so3.to_matrix(q), rtol=0, atol=F64_SERIES
    )


@given(phi=rotation_vectors(max_angle=np.pi))
def test_exp_matches_matrix_exponential(phi: np.ndarray) -> None:
    np.testing.assert_allclose(
        so3.to_matrix(so3.exp(phi)),
        scipy.linalg.expm(so3.hat(phi)),
        rtol=F64_SERIES,
        atol=F64_SERIES,
    )


@given(ax=unit_axes())
def test_log_at_exactly_pi_has_norm_pi(ax: np.ndarray) -> None:
    """At theta = pi (w = 0 up to rounding) Log returns one of the two equivalent answers."""
    phi = so3.log(np.append(ax, 0.0))
    np.testing.assert_allclose(np.linalg.norm(phi), np.pi, rtol=F64_ULPS)
    assert min(np.abs(phi - np.pi * ax).max(), np.abs(phi + np.pi * ax).max()) < 1e-12


@given(q1=stacked(quaternions()), q2=stacked(quaternions()), X=stacked(points()))
def test_mul_conj_act_agree_with_matrices(q1: np.ndarray, q2: np.ndarray, X: np.ndarray) -> None:
    R1, R2 = so3.to_matrix(q1), so3.to_matrix(q2)
    np.testing.assert_allclose(so3.to_matrix(so3.mul(q1, q2)), R1 @ R2, rtol=0, atol=F64_IDENTITY)
    np.testing.assert_allclose(
        so3.act(q1, X), np.einsum("...ij,...j->...i", R1, X), rtol=0, atol=F64_IDENTITY
    )
    np.testing.assert_allclose(
        so3.to_matrix(so3.conj(q1)), np.swapaxes(R1, -1, -2), rtol=0, atol=F64_COPY
    )
    np.testing.assert_allclose(
        so3.mul(q1, so3.conj(q1)), batch_of(np.array([0.0, 0, 0, 1]), (4,)), atol=F64_ULPS
    )
    np.testing.assert_allclose(np.linalg.det(R1), 1.0, rtol=0, atol=F64_IDENTITY)


@given(q1=quaternions(), q2=quaternions(), q3=quaternions())
def test_mul_is_associative(q1: np.ndarray, q2: np.ndarray, q3: np.ndarray) -> None:
    np.testing.assert_allclose(
        so3.mul(so3.mul(q1, q2), q3), so3.mul(q1, so3.mul(q2, q3)), rtol=0, atol=F64_ULPS
    )


@edge_examples(q=lambda th, sg: so3.exp(edge_phi(th)))
@given(q=quaternions())
def test_matrix_roundtrip(q: np.ndarray) -> None:
    back = so3.from_matrix(so3.to_matrix(q))
    assert back[3] >= 0.0
    expected = q if q[3] >= 0 else -q
    if abs(q[3]) < 1e-9:  # theta ~ pi: q and -q both have w ~ 0
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-9
    else:
        np.testing.assert_allclose(back, expected, rtol=0, atol=F64_IDENTITY)


@given(v=points(), w=points())
def test_hat_is_cross_product(v: np.ndarray, w: np.ndarray) -> None:
    np.testing.assert_allclose(so3.hat(v) @ w, np.cross(v, w), rtol=F64_ULPS, atol=F64_IDENTITY)
    np.testing.assert_array_equal(so3.hat(v), -so3.hat(v).T)


def test_normalize_and_its_errors() -> None:
    q = np.array([[0.0, 0.0, 0.0, 3.0], [1.0, 1.0, 1.0, 1.0]])
    np.testing.assert_allclose(so3.normalize(q), [[0, 0, 0, 1.0], [0.5, 0.5, 0.5, 0.5]])
    with pytest.raises(ValueError, match=r"^quat: .*zero norm"):
        so3.normalize(np.zeros(4), "quat")
    with pytest.raises(ValueError, match=r"^q: .*trailing shape"):
        so3.normalize(np.ones(3))


@pytest.mark.parametrize(("theta", "sigma"), EDGE_CASES)
def test_no_nan_at_edge_cases(theta: float, sigma: float) -> None:
    q = so3.exp(edge_phi(theta))
    for out in [q, so3.log(q), so3.log(-q), so3.to_matrix(q), so3.from_matrix(so3.to_matrix(q))]:
        assert np.all(np.isfinite(out))


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=str)
def test_batch_shapes(shape: tuple[int, ...]) -> None:
    phi = batch_of(edge_phi(0.4), shape)
    q = so3.exp(phi)
    X = batch_of(EDGE_POINT, shape)
    calls = {
        "exp": (q, (4,)),
        "log": (so3.log(q), (3,)),
        "mul": (so3.mul(q, q), (4,)),
        "conj": (so3.conj(q), (4,)),
        "act": (so3.act(q, X), (3,)),
        "to_matrix": (so3.to_matrix(q), (3, 3)),
        "from_matrix": (so3.from_matrix(so3.to_matrix(q)), (4,)),
        "hat": (so3.hat(phi), (3, 3)),
        "normalize": (so3.normalize(q), (4,)),
    }
    assert set(calls) == set(so3.__all__)
    for name, (out, tail) in calls.items():
        assert out.shape == (*shape, *tail), name


def test_broadcasting_between_batch_shapes() -> None:
    rng = np.random.default_rng(2)
    q = so3.exp(rng.normal(size=(3, 1, 3)))
    X = rng.normal(size=(1, 4, 3))
    q2 = so3.exp(rng.normal(size=(4, 3)))
    assert so3.act(q, X).shape == (3, 4, 3)
    assert so3.mul(q, q2).shape == (3, 4, 4)
    np.testing.assert_allclose(so3.act(q, X)[2, 1], so3.act(q[2, 0], X[0, 1]))
    np.testing.assert_allclose(so3.mul(q, q2)[1, 3], so3.mul(q[1, 0], q2[3]))


@pytest.mark.parametrize(
    ("call", "bad", "msg"),
    [
        (lambda v: so3.exp(v), np.ones(4), "^phi: .*trailing shape"),
        (lambda v: so3.exp(v), np.array([np.nan, 0, 0]), "^phi: .*non-finite"),
        (lambda v: so3.log(v), np.ones(3), "^q: .*trailing shape"),
        (lambda v: so3.log(v), np.zeros(4), "^q: .*zero norm"),
        (lambda v: so3.log(v), np.array([0, 0, np.inf, 1.0]), "^q: .*non-finite"),
        (lambda v: so3.mul(v, np.ones(4)), np.ones(3), "^q1: .*trailing shape"),
        (lambda v: so3.mul(np.ones(4), v), np.full(4, np.nan), "^q2: .*non-finite"),
        (lambda v: so3.conj(v), np.ones(5), "^q: .*trailing shape"),
        (lambda v: so3.act(v, np.ones(3)), np.ones(3), "^q: .*trailing shape"),
        (lambda v: so3.act(np.ones(4), v), np.ones(4), "^X: .*trailing shape"),
        (lambda v: so3.to_matrix(v), np.ones(3), "^q: .*trailing shape"),
        (lambda v: so3.from_matrix(v), np.ones((4, 4)), "^R: .*trailing shape"),
        (lambda v: so3.from_matrix(v), np.full((3, 3), np.nan), "^R: .*non-finite"),
        (lambda v: so3.hat(v), np.ones(4), "^v: .*trailing shape"),
    ],
)
def test_bad_input_raises_naming_argument(call: object, bad: np.ndarray, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        call(bad)  # type: ignore[operator]
