"""Robust IRLS weights (mslam_ref.robust)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mslam_ref import robust


def test_huber_hand_cases() -> None:
    r = np.array([0.0, 1.0, -1.344, 1.345, -2.69, 13.45])
    np.testing.assert_allclose(robust.huber_weight(r), [1, 1, 1, 1, 0.5, 0.1])


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2), (0,)])
def test_huber_shapes(shape: tuple[int, ...]) -> None:
    r = np.full(shape, 3.0)
    assert robust.huber_weight(r, k=1.5).shape == shape
    assert np.all(robust.huber_weight(r, k=1.5) == 0.5)


@given(st.floats(-1e6, 1e6), st.floats(0.01, 10.0))
def test_huber_is_the_irls_weight_of_the_huber_loss(r: float, k: float) -> None:
    # w(r) = rho'(r) / r for rho = r^2/2 (|r| < k), k|r| - k^2/2 otherwise.
    w = float(robust.huber_weight(np.array(r), k))
    drho = r if abs(r) < k else k * np.sign(r)
    assert 0.0 < w <= 1.0
    assert w * r == pytest.approx(drho, rel=1e-12, abs=1e-12)


def test_tukey() -> None:
    np.testing.assert_allclose(
        robust.tukey_weight(np.array([0.0, 2.0, -2.0, 4.0, 5.0]), c=4.0), [1, 0.5625, 0.5625, 0, 0]
    )


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="k"):
        robust.huber_weight(np.ones(3), k=0.0)
    with pytest.raises(ValueError, match="r"):
        robust.huber_weight(np.array([np.nan]))
    with pytest.raises(ValueError, match="c"):
        robust.tukey_weight(np.ones(3), c=-1.0)
