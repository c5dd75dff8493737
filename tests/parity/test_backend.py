"""mslam_fast.backend against mslam_ref.backend: the 14x14 blocks, gradients and solved poses."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_IDENTITY, F64_SOLVE, tol

from mslam_ref import backend as ref
from mslam_ref import sim3
from mslam_ref.pointmap import backproject

KF, H, W = 4, 24, 32
K = np.array([[30.0, 0.0, 15.5], [0.0, 31.0, 11.5], [0.0, 0.0, 1.0]])


def _graph(seed: int):
    """4 keyframes looking at a wavy wall; random (not necessarily correct) matches with noise,
    invalid entries, low qualities and low confidences, so every branch is exercised."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    T = sim3.exp(np.concatenate([rng.normal(0, 0.1, (KF, 6)), rng.normal(0, 0.05, (KF, 1))], 1))
    X = np.stack(
        [backproject(2.0 + 0.3 * np.sin(u / 4.0 + k) + 0.2 * np.cos(v / 3.0), K) for k in range(KF)]
    )
    X = X + rng.normal(0, 0.01, X.shape)
    X[0, 0, :3, 2] = -1.0  # points behind the camera
    C = rng.uniform(0.0, 3.0, (KF, H, W))
    ii = np.array([0, 1, 1, 2, 3, 0])
    jj = np.array([1, 0, 2, 1, 0, 3])
    N = H * W
    idx = np.clip(np.arange(N)[None] + rng.integers(-40, 40, (len(ii), N)), 0, N - 1)
    valid = rng.random((len(ii), N)) < 0.9
    Q = rng.uniform(1.0, 4.0, (len(ii), N))
    return T, X, C, ii, jj, idx, valid, Q


@pytest.mark.parametrize("calibrated", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_linearize_parity(fast: str, calibrated: bool, seed: int) -> None:
    from mslam_fast import backend as fst

    T, X, C, ii, jj, idx, valid, Q = _graph(seed)
    Kc = K if calibrated else None
    graph = ref.pose_graph(X, C, ii, jj, idx, valid, Q, Kc)
    Hr, gr, cr = ref.linearize(T, graph, ref.BackendConfig())
    Hf, gf, cf = fst.linearize(T, graph, ref.BackendConfig())
    assert Hf.shape == (6, 4, 7, 7) and gf.shape == (6, 2, 7)
    t = tol("backend", fast)
    scale = np.abs(Hr).max(axis=(1, 2, 3), keepdims=True)
    assert np.all(np.abs(Hf - Hr) <= t["atol"] * scale + t["rtol"] * np.abs(Hr))
    gscale = np.abs(gr).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(gf - gr) <= t["atol"] * gscale + t["rtol"] * np.abs(gr))
    assert cf == pytest.approx(cr, rel=t["rtol"])


@pytest.mark.parametrize("calibrated", [False, True])
def test_solve_parity(fast: str, calibrated: bool) -> None:
    from mslam_fast import backend as fst

    T, X, C, ii, jj, idx, valid, Q = _graph(2)
    Kc = K if calibrated else None
    cfg = ref.BackendConfig(max_iters=3)
    graph = ref.pose_graph(X, C, ii, jj, idx, valid, Q, Kc)
    Tr, ir = ref.solve(T, graph, cfg)
    Tf, inf = fst.solve(T, graph, cfg)
    assert inf.iterations == ir.iterations and inf.keyframes == ir.keyframes
    np.testing.assert_array_equal(Tf[0], T[0])
    np.testing.assert_allclose(Tf, Tr, rtol=0, atol=tol("backend", fast)["atol"] * 10)


def test_empty_and_bad(fast: str) -> None:
    from mslam_fast import backend as fst

    T, X, C, ii, jj, idx, valid, Q = _graph(3)
    Hs, gs, cost = fst.linearize(T, ref.pose_graph(X, C, ii[:0], jj[:0], idx[:0], valid[:0], Q[:0]))
    assert Hs.shape == (0, 4, 7, 7) and gs.shape == (0, 2, 7) and cost == 0.0
    with pytest.raises(ValueError, match="T_WC"):
        fst.linearize(T[:2], ref.pose_graph(X, C, ii, jj, idx, valid, Q))


@pytest.mark.parametrize("calibrated", [False, True])
def test_residual_pixel_subset(fast: str, calibrated: bool) -> None:
    """``pixels`` (a subset of j's pixels as the columns) equals masking every other pixel,
    in the reference and in the fast kernel."""
    from mslam_fast import backend as fst

    T, X, C, ii, jj, idx, valid, Q = _graph(4)
    Kc = K if calibrated else None
    pixels = np.flatnonzero(np.random.default_rng(5).random(H * W) < 0.3)
    masked = np.zeros_like(valid)
    masked[:, pixels] = valid[:, pixels]
    full = ref.linearize(T, ref.pose_graph(X, C, ii, jj, idx, masked, Q, Kc))
    sub_graph = ref.pose_graph(
        X, C, ii, jj, idx[:, pixels], valid[:, pixels], Q[:, pixels], Kc, pixels
    )
    sub = ref.linearize(T, sub_graph)
    np.testing.assert_allclose(sub[0], full[0], rtol=F64_IDENTITY, atol=F64_SOLVE)
    np.testing.assert_allclose(sub[1], full[1], rtol=F64_IDENTITY, atol=F64_SOLVE)
    assert sub[2] == pytest.approx(full[2], rel=1e-12)
    Hf, gf, cf = fst.linearize(T, sub_graph)
    t = tol("backend", fast)
    scale = np.abs(sub[0]).max(axis=(1, 2, 3), keepdims=True)
    assert np.all(np.abs(Hf - sub[0]) <= t["atol"] * scale + t["rtol"] * np.abs(sub[0]))
    gscale = np.abs(sub[1]).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(gf - sub[1]) <= t["atol"] * gscale + t["rtol"] * np.abs(sub[1]))
    assert cf == pytest.approx(sub[2], rel=t["rtol"])
    with pytest.raises(ValueError, match="idx"):
        ref.pose_graph(X, C, ii, jj, idx, valid, Q, Kc, pixels)  # columns must match pixels
    with pytest.raises(ValueError, match="pixels"):
        ref.pose_graph(X, C, ii, jj, idx[:, :2], valid[:, :2], Q[:, :2], Kc, [0, H * W])
