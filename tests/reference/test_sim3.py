"""Properties of ``mslam_ref.sim3``: group axioms, Exp/Log, adjoint, Jacobian, shapes, bad input."""

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
    edge_element,
    edge_examples,
    edge_tangent,
    points,
    sim3_elements,
    stacked,
    tangents,
    tiny_tangents,
)
from tolerances import (
    F64_COPY,
    F64_IDENTITY,
    F64_IDENTITY_POINTS,
    F64_SERIES,
    F64_SHORT_CHAIN,
    F64_SOLVE,
    FD_ATOL,
)

from mslam_ref import sim3, so3


def hat4(xi: np.ndarray) -> np.ndarray:
    """4x4 Lie-algebra matrix ``[[phi^ + sigma I, tau], [0, 0]]``."""
    M = np.zeros((*xi.shape[:-1], 4, 4))
    M[..., :3, :3] = so3.hat(xi[..., 3:6]) + xi[..., 6, None, None] * np.eye(3)
    M[..., :3, 3] = xi[..., :3]
    return M


def assert_same_element(A: np.ndarray, B: np.ndarray, tol: float = 1e-9) -> None:
    """Equal as transforms (compares 4x4 matrices, so q and -q are the same element)."""
    MA, MB = sim3.to_matrix(A), sim3.to_matrix(B)
    scale = max(1.0, float(np.max(np.abs(MB))))
    np.testing.assert_allclose(MA, MB, rtol=0, atol=tol * scale)


# --- group axioms ---------------------------------------------------------------------------


@given(A=stacked(sim3_elements()), B=stacked(sim3_elements()), C=stacked(sim3_elements()))
def test_mul_is_associative(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> None:
    assert_same_element(sim3.mul(sim3.mul(A, B), C), sim3.mul(A, sim3.mul(B, C)))


@given(T=stacked(sim3_elements()), X=stacked(points()))
def test_identity(T: np.ndarray, X: np.ndarray) -> None:
    eye = sim3.identity((4,))
    np.testing.assert_allclose(sim3.mul(eye, T), T, rtol=0, atol=F64_COPY)
    np.testing.assert_allclose(sim3.mul(T, eye), T, rtol=0, atol=F64_COPY)
    np.testing.assert_array_equal(sim3.act(eye, X), X)
    np.testing.assert_array_equal(sim3.exp(np.zeros(7)), sim3.identity())


@edge_examples(
    T=lambda th, sg: batch_of(edge_element(th, sg), (4,)),
    X=lambda th, sg: batch_of(EDGE_POINT, (4,)),
)
@given(T=stacked(sim3_elements()), X=stacked(points()))
def test_inverse(T: np.ndarray, X: np.ndarray) -> None:
    eye = sim3.identity((4,))
    assert_same_element(sim3.mul(T, sim3.inv(T)), eye)
    assert_same_element(sim3.mul(sim3.inv(T), T), eye)
    np.testing.assert_allclose(sim3.act(sim3.inv(T), sim3.act(T, X)), X, rtol=0, atol=F64_SOLVE)
    np.testing.assert_allclose(
        sim3.to_matrix(sim3.inv(T)),
        np.linalg.inv(sim3.to_matrix(T)),
        rtol=F64_SERIES,
        atol=F64_SERIES,
    )


@given(A=stacked(sim3_elements()), B=stacked(sim3_elements()), X=stacked(points()))
def test_mul_is_matrix_product_and_composes_actions(
    A: np.ndarray, B: np.ndarray, X: np.ndarray
) -> None:
    AB = sim3.mul(A, B)
    np.testing.assert_allclose(
        sim3.to_matrix(AB),
        sim3.to_matrix(A) @ sim3.to_matrix(B),
        rtol=F64_IDENTITY,
        atol=F64_IDENTITY,
    )
    np.testing.assert_allclose(
        sim3.act(AB, X), sim3.act(A, sim3.act(B, X)), rtol=F64_IDENTITY, atol=F64_IDENTITY_POINTS
    )


# --- Exp / Log --------------------------------------------------------------------------------


@edge_examples(xi=lambda th, sg: edge_tangent(th, sg))
@given(xi=tangents())
def test_log_exp_roundtrip(xi: np.ndarray) -> None:
    """Log(Exp(xi)) = xi for ||phi|| < pi (Log is unique there)."""
    np.testing.assert_allclose(sim3.log(sim3.exp(xi)), xi, rtol=F64_SOLVE, atol=F64_SOLVE)


@given(xi=tiny_tangents())
def test_log_exp_roundtrip_near_identity(xi: np.ndarray) -> None:
    """Entries <= 1e-7: absolute 1e-15 (s = e^sigma is stored, so log s carries ~1e-16)."""
    np.testing.assert_allclose(sim3.log(sim3.exp(xi)), xi, rtol=F64_SOLVE, atol=F64_COPY)


@given(T=sim3_elements())
def test_exp_log_roundtrip(T: np.ndarray) -> None:
    xi = sim3.log(T)
    assert np.linalg.norm(xi[3:6]) <= np.pi + 1e-12
    assert_same_element(sim3.exp(xi), T, tol=1e-9)


@edge_examples(xi=lambda th, sg: edge_tangent(th, sg))
@given(xi=tangents(max_angle=np.pi))
def test_exp_matches_matrix_exponential(xi: np.ndarray) -> None:
    """Exp(xi) equals scipy's expm of the 4x4 hat matrix."""
    np.testing.assert_allclose(
        sim3.to_matrix(sim3.exp(xi)), scipy.linalg.expm(hat4(xi)), rtol=F64_SOLVE, atol=F64_SOLVE
    )


@given(xi=tangents(max_angle=np.pi))
def test_exp_gives_unit_quaternion_and_w_nonnegative(xi: np.ndarray) -> None:
    q = sim3.exp(xi)[3:7]
    assert abs(np.linalg.norm(q) - 1.0) < 1e-14
    assert q[3] >= 0.0


def test_exp_of_tiny_tangents_uses_series_without_nan() -> None:
    xi = np.array([[1.0, 2.0, 3.0, 1e-9, -1e-9, 0.0, 1e-9], [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.0]])
    T = sim3.exp(xi)
    assert np.all(np.isfinite(T))
    np.testing.assert_allclose(T[1], [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 1.0], atol=0)


# --- adjoint -----------------------------------------------------------------------------------


@edge_examples(T=edge_element, a=lambda th, sg: edge_tangent(0.5, 0.1))
@given(T=sim3_elements(), a=tangents(max_angle=1.0, tau_bound=1.0, sigma_bound=0.5))
def test_adjoint_identity(T: np.ndarray, a: np.ndarray) -> None:
    """T Exp(a) T^-1 = Exp(Ad(T) a), and the algebra form T hat(a) T^-1 = hat(Ad(T) a)."""
    MT = sim3.to_matrix(T)
    Ad = sim3.adjoint(T)
    lhs = MT @ sim3.to_matrix(sim3.exp(a)) @ np.linalg.inv(MT)
    np.testing.assert_allclose(
        lhs, sim3.to_matrix(sim3.exp(Ad @ a)), rtol=F64_SOLVE, atol=F64_SOLVE * np.abs(lhs).max()
    )
    np.testing.assert_allclose(
        MT @ hat4(a) @ np.linalg.inv(MT), hat4(Ad @ a), rtol=F64_SOLVE, atol=F64_SOLVE
    )


@given(T=stacked(sim3_elements()), J=stacked(tangents()))
def test_adjoint_inv_apply(T: np.ndarray, J: np.ndarray) -> None:
    """adjoint_inv_apply(T, J) == J @ inv(adjoint(T)), and == J @ adjoint(T^-1)."""
    expected = np.einsum("...i,...ij->...j", J, np.linalg.inv(sim3.adjoint(T)))
    got = sim3.adjoint_inv_apply(T, J)
    np.testing.assert_allclose(got, expected, rtol=F64_SOLVE, atol=F64_SOLVE)
    np.testing.assert_allclose(
        got,
        np.einsum("...i,...ij->...j", J, sim3.adjoint(sim3.inv(T))),
        rtol=F64_SOLVE,
        atol=F64_SOLVE,
    )


# --- retraction and the point Jacobian ----------------------------------------------------------


@given(T=sim3_elements(), xi=tangents())
def test_retract_is_left_multiplication(T: np.ndarray, xi: np.ndarray) -> None:
    out = sim3.retract(T, xi)
    assert_same_element(out, sim3.mul(sim3.exp(xi), T))
    assert abs(np.linalg.norm(out[3:7]) - 1.0) < 1e-14


@edge_examples(T=edge_element, X=lambda th, sg: EDGE_POINT)
@given(T=sim3_elements(), X=points())
def test_act_and_jacobian_matches_finite_differences(T: np.ndarray, X: np.ndarray) -> None:
    """Columns of J against central differences of act(retract(T, +-eps e_k), X)."""
    P, J = sim3.act_and_jacobian(T, X)
    np.testing.assert_array_equal(P, sim3.act(T, X))
    eps = 1e-6
    E = eps * np.eye(7)
    fd = (sim3.act(sim3.retract(T, E), X) - sim3.act(sim3.retract(T, -E), X)) / (2 * eps)
    np.testing.assert_allclose(J, fd.T, rtol=0, atol=FD_ATOL * (1.0 + np.abs(P).max()))


# --- matrices ------------------------------------------------------------------------------------


@edge_examples(T=edge_element)
@given(T=sim3_elements())
def test_matrix_roundtrip(T: np.ndarray) -> None:
    M = sim3.to_matrix(T)
    back = sim3.from_matrix(M)
    assert back[6] >= 0.0
    np.testing.assert_allclose(
        back[[0, 1, 2, 7]], T[[0, 1, 2, 7]], rtol=F64_IDENTITY, atol=F64_IDENTITY
    )
    q = T[3:7] if T[6] >= 0 else -T[3:7]
    np.testing.assert_allclose(back[3:7], q, rtol=0, atol=F64_SOLVE)
    np.testing.assert_allclose(sim3.to_matrix(back), M, rtol=F64_IDENTITY, atol=F64_IDENTITY)


def test_from_matrix_rejects_reflections() -> None:
    M = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="M"):
        sim3.from_matrix(M)


# --- edge cases, shapes, broadcasting -------------------------------------------------------------


@pytest.mark.parametrize(("theta", "sigma"), EDGE_CASES)
def test_no_nan_at_edge_cases(theta: float, sigma: float) -> None:
    xi = edge_tangent(theta, sigma)
    T = sim3.exp(xi)
    outs = [
        T,
        sim3.log(T),
        sim3.inv(T),
        sim3.mul(T, T),
        sim3.act(T, EDGE_POINT),
        *sim3.act_and_jacobian(T, EDGE_POINT),
        sim3.adjoint(T),
        sim3.adjoint_inv_apply(T, xi),
        sim3.retract(T, xi),
        sim3.to_matrix(T),
        sim3.from_matrix(sim3.to_matrix(T)),
    ]
    for out in outs:
        assert np.all(np.isfinite(out))


def _calls(shape: tuple[int, ...]) -> dict[str, tuple[object, tuple[int, ...]]]:
    """Every public function on inputs of batch ``shape``, with its expected output tail."""
    T = batch_of(edge_element(0.7, 0.2), shape)
    xi = batch_of(edge_tangent(0.3, -0.1), shape)
    X = batch_of(EDGE_POINT, shape)
    return {
        "identity": (sim3.identity(shape), (8,)),
        "exp": (sim3.exp(xi), (8,)),
        "log": (sim3.log(T), (7,)),
        "mul": (sim3.mul(T, T), (8,)),
        "inv": (sim3.inv(T), (8,)),
        "act": (sim3.act(T, X), (3,)),
        "act_and_jacobian.P": (sim3.act_and_jacobian(T, X)[0], (3,)),
        "act_and_jacobian.J": (sim3.act_and_jacobian(T, X)[1], (3, 7)),
        "adjoint": (sim3.adjoint(T), (7, 7)),
        "adjoint_inv_apply": (sim3.adjoint_inv_apply(T, xi), (7,)),
        "retract": (sim3.retract(T, xi), (8,)),
        "to_matrix": (sim3.to_matrix(T), (4, 4)),
        "from_matrix": (sim3.from_matrix(sim3.to_matrix(T)), (8,)),
        "validate": (sim3.validate(T), (8,)),
    }


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=str)
def test_batch_shapes(shape: tuple[int, ...]) -> None:
    calls = _calls(shape)
    assert {k.split(".")[0] for k in calls} == set(sim3.__all__)
    for name, (out, tail) in calls.items():
        assert out.shape == (*shape, *tail), name
        assert out.dtype == np.float64, name


def test_broadcasting_between_batch_shapes() -> None:
    rng = np.random.default_rng(1)
    T = sim3.exp(rng.normal(size=(3, 1, 7)))
    X = rng.normal(size=(1, 4, 3))
    B = sim3.exp(rng.normal(size=(4, 7)))
    J = rng.normal(size=(4, 7))
    assert sim3.act(T, X).shape == (3, 4, 3)
    assert sim3.mul(T, B).shape == (3, 4, 8)
    assert sim3.adjoint_inv_apply(T, J).shape == (3, 4, 7)
    assert sim3.retract(T, J).shape == (3, 4, 8)
    P, Jac = sim3.act_and_jacobian(T, X)
    assert P.shape == (3, 4, 3) and Jac.shape == (3, 4, 3, 7)
    for i in range(3):
        for j in range(4):
            np.testing.assert_allclose(sim3.act(T, X)[i, j], sim3.act(T[i, 0], X[0, j]))
            np.testing.assert_allclose(sim3.mul(T, B)[i, j], sim3.mul(T[i, 0], B[j]))
            np.testing.assert_allclose(
                sim3.adjoint_inv_apply(T, J)[i, j], sim3.adjoint_inv_apply(T[i, 0], J[j])
            )


# --- bad input ------------------------------------------------------------------------------------

GOOD_T = np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0, 1.5])


def bad_inputs() -> list[tuple[str, object, str]]:
    """(case id, value, regex the error must contain) for a Sim(3) argument."""
    nan_T, inf_T, zero_s, neg_s, zero_q = (GOOD_T.copy() for _ in range(5))
    nan_T[0] = np.nan
    inf_T[4] = np.inf
    zero_s[7] = 0.0
    neg_s[7] = -2.0
    zero_q[3:7] = 0.0
    return [
        ("shape7", GOOD_T[:7], "trailing shape"),
        ("shape_scalar", 1.0, "trailing shape"),
        ("nan", nan_T, "non-finite"),
        ("inf", inf_T, "non-finite"),
        ("zero_scale", zero_s, "scale"),
        ("negative_scale", neg_s, "scale"),
        ("zero_quaternion", zero_q, "zero norm"),
    ]


BAD = bad_inputs()


@pytest.mark.parametrize(("case", "bad", "msg"), BAD, ids=[b[0] for b in BAD])
def test_bad_element_raises_naming_argument(case: str, bad: object, msg: str) -> None:
    X = np.ones(3)
    J = np.ones(7)
    for fn, name in [
        (lambda T: sim3.log(T), "T"),
        (lambda T: sim3.inv(T), "T"),
        (lambda T: sim3.act(T, X), "T"),
        (lambda T: sim3.act_and_jacobian(T, X), "T"),
        (lambda T: sim3.adjoint(T), "T"),
        (lambda T: sim3.adjoint_inv_apply(T, J), "T"),
        (lambda T: sim3.retract(T, J), "T"),
        (lambda T: sim3.to_matrix(T), "T"),
        (lambda A: sim3.mul(A, GOOD_T), "A"),
        (lambda B: sim3.mul(GOOD_T, B), "B"),
    ]:
        with pytest.raises(ValueError, match=rf"^{name}: .*{msg}"):
            fn(bad)


GOOD_XI = np.arange(1.0, 8.0) * 0.1
NAN_XI = GOOD_XI * np.nan


@pytest.mark.parametrize(
    ("call", "bad", "msg"),
    [
        (lambda v: sim3.exp(v), np.ones(6), "^xi: .*trailing shape"),
        (lambda v: sim3.exp(v), NAN_XI, "^xi: .*non-finite"),
        (lambda v: sim3.retract(GOOD_T, v), np.ones(8), "^xi: .*trailing shape"),
        (lambda v: sim3.retract(GOOD_T, v), NAN_XI, "^xi: .*non-finite"),
        (lambda v: sim3.adjoint_inv_apply(GOOD_T, v), np.ones(6), "^J: .*trailing shape"),
        (lambda v: sim3.adjoint_inv_apply(GOOD_T, v), NAN_XI, "^J: .*non-finite"),
        (lambda v: sim3.act(GOOD_T, v), np.ones(4), "^X: .*trailing shape"),
        (lambda v: sim3.act(GOOD_T, v), NAN_XI[:3], "^X: .*non-finite"),
        (lambda v: sim3.act_and_jacobian(GOOD_T, v), np.ones(2), "^X: .*trailing shape"),
        (lambda v: sim3.from_matrix(v), np.eye(3), "^M: .*trailing shape"),
        (lambda v: sim3.from_matrix(v), np.full((4, 4), np.inf), "^M: .*non-finite"),
    ],
)
def test_bad_vectors_raise_naming_argument(call: object, bad: np.ndarray, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        call(bad)  # type: ignore[operator]


@given(T=sim3_elements(), X=points())
def test_unnormalised_quaternion_is_normalised(T: np.ndarray, X: np.ndarray) -> None:
    """Scaling q by 3 changes nothing: every function normalises it on input."""
    T3 = T.copy()
    T3[3:7] *= 3.0
    np.testing.assert_allclose(
        sim3.act(T3, X), sim3.act(T, X), rtol=F64_SHORT_CHAIN, atol=F64_SHORT_CHAIN
    )
    np.testing.assert_allclose(sim3.validate(T3), sim3.validate(T), rtol=F64_COPY, atol=F64_COPY)
