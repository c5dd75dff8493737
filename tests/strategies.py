"""Hypothesis strategies for Sim(3)/SO(3) tests: group elements, tangents, points, edge cases.

Sim(3) elements ``[t, q_xyzw, s]`` (shape (8,)) are drawn four ways, combined by
:func:`sim3_elements`:

* :func:`sim3_from_tangent` — ``Exp`` of a bounded tangent (||phi|| < pi, |sigma| <= 1.5);
* :func:`sim3_uniform` — a uniformly random rotation (normalised 4-D Gaussian, so q covers the
  whole sphere including w < 0), a Gaussian translation and a log-normal scale;
* :func:`sim3_near_identity` — ``Exp`` of a tangent whose entries are at most 1e-7 (the series
  branches of Exp/Log);
* :func:`sim3_near_pi` — rotations by ``pi - delta`` with delta in [1e-12, 1e-2] or 0.

Theseus-style explicit examples: :data:`EDGE_CASES` lists (theta, sigma) pairs, with theta in
{0, 1e-5, 3e-3, pi - 1e-11} and sigmas on both sides of the 1e-6 series threshold;
:func:`edge_examples` attaches one ``@example`` per case to a ``@given`` test.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from hypothesis import example
from hypothesis import strategies as st

from mslam_ref import sim3, so3

#: (theta, sigma) of the explicit examples: rotation angle and log-scale.
EDGE_CASES: tuple[tuple[float, float], ...] = (
    (0.0, 0.0),
    (0.0, 0.4),
    (1e-5, 1e-7),
    (3e-3, 2e-6),
    (np.pi - 1e-11, 0.5),
)
_EDGE_AXIS = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
_EDGE_TAU = np.array([0.3, -1.2, 2.0])
EDGE_POINT = np.array([0.7, -0.4, 2.5])


def edge_tangent(theta: float, sigma: float) -> np.ndarray:
    """A fixed tangent ``[tau, theta * axis, sigma]`` with rotation angle ``theta``."""
    return np.concatenate([_EDGE_TAU, theta * _EDGE_AXIS, [sigma]])


def edge_element(theta: float, sigma: float) -> np.ndarray:
    """``Exp`` of :func:`edge_tangent`."""
    return sim3.exp(edge_tangent(theta, sigma))


def edge_examples(**makers: Callable[[float, float], Any]) -> Callable[[Any], Any]:
    """Attach ``@example(name=maker(theta, sigma), ...)`` for every (theta, sigma) in EDGE_CASES.

    Example: ``@edge_examples(T=edge_element, X=lambda th, sg: EDGE_POINT)`` above ``@given``.
    """

    def deco(f: Any) -> Any:
        for theta, sigma in EDGE_CASES:
            f = example(**{k: m(theta, sigma) for k, m in makers.items()})(f)
        return f

    return deco


def _vec(n: int, lo: float, hi: float) -> st.SearchStrategy[np.ndarray]:
    # No subnormals: they are flushed to zero by ordinary arithmetic (x + 0.0 * y keeps them,
    # s R X + t may not), which is not a property of the maps under test.
    fl = st.floats(lo, hi, allow_nan=False, allow_infinity=False, allow_subnormal=False)
    return st.lists(fl, min_size=n, max_size=n).map(lambda v: np.array(v, dtype=np.float64))


def points(bound: float = 10.0) -> st.SearchStrategy[np.ndarray]:
    """A 3-D point with entries in [-bound, bound]."""
    return _vec(3, -bound, bound)


def unit_axes() -> st.SearchStrategy[np.ndarray]:
    """A unit 3-vector (rejects near-zero draws)."""
    return (
        _vec(3, -1.0, 1.0)
        .filter(lambda v: np.linalg.norm(v) > 1e-3)
        .map(lambda v: v / np.linalg.norm(v))
    )


def rotation_vectors(max_angle: float = np.pi - 1e-6) -> st.SearchStrategy[np.ndarray]:
    """``axis * angle`` with angle in [0, max_angle], plus tiny and near-pi angles."""
    angles = st.one_of(
        st.floats(0.0, max_angle),
        st.floats(0.0, 1e-6, allow_subnormal=False),
        st.floats(-12.0, -2.0).map(lambda e: np.pi - 10.0**e),
    ).filter(lambda a: a <= max_angle)
    return st.builds(lambda ax, a: ax * a, unit_axes(), angles)


def tangents(
    max_angle: float = np.pi - 1e-6, tau_bound: float = 5.0, sigma_bound: float = 1.5
) -> st.SearchStrategy[np.ndarray]:
    """A Sim(3) tangent ``[tau, phi, sigma]`` with ||phi|| <= max_angle (so Log is unique)."""
    sigmas = st.one_of(
        st.floats(-sigma_bound, sigma_bound, allow_subnormal=False),
        st.floats(-2e-6, 2e-6, allow_subnormal=False),
    )
    return st.builds(
        lambda tau, phi, sg: np.concatenate([tau, phi, [sg]]),
        _vec(3, -tau_bound, tau_bound),
        rotation_vectors(max_angle),
        sigmas,
    )


def tiny_tangents(scale: float = 1e-7) -> st.SearchStrategy[np.ndarray]:
    """A tangent with every entry in [-scale, scale] (Exp/Log series branches)."""
    return _vec(7, -scale, scale)


def sim3_from_tangent() -> st.SearchStrategy[np.ndarray]:
    """``Exp`` of a bounded tangent."""
    return tangents().map(sim3.exp)


def _uniform(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    t = rng.normal(scale=3.0, size=3)
    s = np.exp(np.clip(rng.normal(scale=0.7), -2.5, 2.5))
    return np.concatenate([t, q, [s]])


def sim3_uniform() -> st.SearchStrategy[np.ndarray]:
    """Uniform random rotation (any sign of w), N(0, 3^2) translation, log-normal scale."""
    return st.integers(0, 2**32 - 1).map(_uniform)


def sim3_near_identity(scale: float = 1e-7) -> st.SearchStrategy[np.ndarray]:
    """``Exp`` of a tangent with entries of at most ``scale``."""
    return tiny_tangents(scale).map(sim3.exp)


def sim3_near_pi() -> st.SearchStrategy[np.ndarray]:
    """A rotation by ``pi - delta`` (delta = 0 or 10^[-12, -2]) with random t and s."""
    deltas = st.one_of(st.just(0.0), st.floats(-12.0, -2.0).map(lambda e: 10.0**e))
    return st.builds(
        lambda ax, d, t, lsg: np.concatenate([t, so3.exp(ax * (np.pi - d)), [np.exp(lsg)]]),
        unit_axes(),
        deltas,
        _vec(3, -5.0, 5.0),
        st.floats(-1.5, 1.5),
    )


def sim3_elements() -> st.SearchStrategy[np.ndarray]:
    """Any of the four kinds of Sim(3) element."""
    return st.one_of(sim3_from_tangent(), sim3_uniform(), sim3_near_identity(), sim3_near_pi())


def quaternions() -> st.SearchStrategy[np.ndarray]:
    """Unit quaternions: the rotation parts of :func:`sim3_elements`."""
    return sim3_elements().map(lambda T: T[3:7].copy())


def stacked(elements: st.SearchStrategy[np.ndarray], n: int = 4) -> st.SearchStrategy[np.ndarray]:
    """A batch ``(n, k)`` of independently drawn elements (more cases per example)."""
    return st.lists(elements, min_size=n, max_size=n).map(np.stack)


#: Batch shapes every vectorised function is checked on.
BATCH_SHAPES: tuple[tuple[int, ...], ...] = ((), (1,), (3, 1, 2), (0,))


def batch_of(x: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``x`` (k,) repeated into shape ``(*shape, k)`` (a writable copy)."""
    return np.broadcast_to(x, (*shape, x.shape[-1])).copy()
