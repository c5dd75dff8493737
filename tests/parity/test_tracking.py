"""mslam_fast.tracking against mslam_ref.tracking: H, g, cost and solved poses, both residuals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tolerances import tol

from mslam_ref import sim3
from mslam_ref import tracking as ref
from mslam_ref.pointmap import backproject

H, W = 48, 64
K = np.array([[50.0, 0.0, 31.5], [0.0, 52.0, 23.5], [0.0, 0.0, 1.0]])


def _problem(seed: int):
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    X_k = backproject(2.0 + 0.4 * np.sin(u / 7.0 + seed) + 0.3 * np.cos(v / 5.0), K)
    T = sim3.exp(
        np.concatenate([rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3), rng.normal(0, 0.05, 1)])
    )
    X_f = sim3.act(sim3.inv(T), X_k.reshape(-1, 3)) + rng.normal(0, 0.01, (H * W, 3))
    X_f[rng.random(H * W) < 0.03] += 1.0  # outliers (Huber active)
    X_f[:5] = sim3.act(sim3.inv(T), np.array([0.0, 0.0, -1.0]))  # behind the camera
    Q = rng.uniform(0.5, 4.0, H * W)
    valid = rng.random(H * W) < 0.9
    T1 = sim3.retract(T, rng.normal(0, 0.02, 7))
    return X_k, X_f, Q, valid, T, T1


def _close(a, b, fp, scale=None):
    t = tol("tracking", fp)
    atol = t["atol"] * (np.abs(a).max() if scale is None else scale)
    np.testing.assert_allclose(b, a, rtol=t["rtol"], atol=atol)


@settings(suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture])  # fmt: skip
@given(seed=st.integers(0, 2**16), calibrated=st.booleans())
def test_linearize_parity(fast: str, seed: int, calibrated: bool) -> None:
    from mslam_fast import tracking as fst

    X_k, X_f, Q, valid, _, T1 = _problem(seed)
    Kc = K if calibrated else None
    Hr, gr, cr = ref.linearize(T1, X_f, X_k, Q, valid, ref.TrackingConfig(), Kc)
    Hf, gf, cf = fst.linearize(T1, X_f, X_k, Q, valid, ref.TrackingConfig(), Kc)
    assert Hf.shape == (7, 7) and gf.shape == (7,) and isinstance(cf, float)
    _close(Hr, Hf, fast)
    _close(gr, gf, fast, np.abs(Hr).max() * 1e-3)
    assert cf == pytest.approx(cr, rel=tol("tracking", fast)["rtol"])


@pytest.mark.parametrize("calibrated", [False, True])
def test_solve_parity(fast: str, calibrated: bool) -> None:
    from mslam_fast import tracking as fst

    X_k, X_f, Q, valid, _, _ = _problem(11)
    Kc = K if calibrated else None
    Tr, ir = ref.solve(X_f, X_k, Q, valid, sim3.identity(), ref.TrackingConfig(), Kc)
    Tf, inf = fst.solve(X_f, X_k, Q, valid, sim3.identity(), ref.TrackingConfig(), Kc)
    assert not inf.failed and inf.converged == ir.converged
    if fast == "f64":
        assert inf.iterations == ir.iterations
    _close(Tr, Tf, fast, 1.0)


def test_failure_and_empty(fast: str) -> None:
    from mslam_fast import tracking as fst

    X_k, X_f, Q, valid, T, _ = _problem(3)
    T_est, info = fst.solve(X_f, X_k, Q, np.zeros_like(valid), T)
    assert info.failed
    np.testing.assert_array_equal(T_est, sim3.validate(T))
    Hm, g, c = fst.linearize(T, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool))
    assert np.all(Hm == 0) and np.all(g == 0) and c == 0.0
    with pytest.raises(ValueError, match="X_k"):
        fst.linearize(T, X_f, X_k.reshape(-1, 3), Q, valid, ref.TrackingConfig(), K)
