"""Tracking (mslam_ref.tracking): residuals, Jacobians, the IRLS system, the driver's stopping
and failure rules, pose recovery, and the frontend masks and keyframe test."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from tolerances import (
    F64_IDENTITY,
    F64_SERIES,
    F64_SOLVE,
    FD_COST_GRADIENT,
    FD_LOOSE,
    FD_RTOL,
    FD_TRACKING,
)

from mslam_ref import sim3, tracking
from mslam_ref.pointmap import backproject
from mslam_ref.tracking import TrackingConfig

H, W = 24, 32
K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])


def _problem(seed: int, noise: float = 0.0, outliers: float = 0.0):
    """Keyframe pointmap on its rays, frame points exactly (or noisily) matched."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    depth = 2.0 + 0.4 * np.sin(u / 5.0 + seed) + 0.3 * np.cos(v / 4.0)
    X_k = backproject(depth, K)
    xi = np.concatenate([rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3), [rng.normal(0, 0.05)]])
    T = sim3.exp(xi)
    X_f = sim3.act(sim3.inv(T), X_k.reshape(-1, 3))
    X_f = X_f * (1 + rng.normal(0, noise, (len(X_f), 1))) + rng.normal(0, noise, X_f.shape)
    bad = rng.random(len(X_f)) < outliers
    X_f[bad] += rng.normal(0, 0.5, (bad.sum(), 3))
    return X_k, X_f, T


def _fd(fun, T: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    cols = []
    for k in range(7):
        e = np.zeros(7)
        e[k] = eps
        cols.append((fun(sim3.retract(T, e)) - fun(sim3.retract(T, -e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def test_config_defaults() -> None:
    c = TrackingConfig()
    assert (c.min_match_frac, c.max_iters, c.C_conf, c.Q_conf) == (0.05, 50, 0.0, 1.5)
    assert (c.rel_error, c.delta_norm, c.huber, c.match_frac_thresh) == (1e-3, 1e-3, 1.345, 0.333)
    assert (c.sigma_ray, c.sigma_dist, c.sigma_pixel, c.sigma_depth) == (0.003, 10.0, 1.0, 10.0)
    assert (c.sigma_point, c.pixel_border, c.depth_eps) == (0.05, -10, 1e-6)
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.max_iters = 3  # type: ignore[misc]


@given(st.integers(0, 10_000))
def test_ray_dist_jacobian_matches_finite_differences(seed: int) -> None:
    X_k, X_f, T = _problem(seed % 97)
    T1 = sim3.retract(T, np.random.default_rng(seed).normal(0, 0.05, 7))
    r, J = tracking.ray_dist_residual_and_jacobian(T1, X_f[:40], X_k.reshape(-1, 3)[:40])
    assert r.shape == (40, 4) and J.shape == (40, 4, 7)
    fd = _fd(
        lambda TT: tracking.ray_dist_residual_and_jacobian(TT, X_f[:40], X_k.reshape(-1, 3)[:40])[
            0
        ],
        T1,
    )
    np.testing.assert_allclose(J, fd, atol=FD_TRACKING, rtol=FD_RTOL)


def test_residuals_zero_at_truth_and_origin_is_finite() -> None:
    X_k, X_f, T = _problem(1)
    r, _ = tracking.ray_dist_residual_and_jacobian(T, X_f, X_k)
    np.testing.assert_allclose(r, 0.0, atol=F64_IDENTITY)
    r0, J0 = tracking.ray_dist_residual_and_jacobian(
        sim3.identity(), np.zeros((2, 3)), np.ones((2, 3))
    )
    assert np.all(np.isfinite(r0)) and np.all(J0 == 0)


@pytest.mark.parametrize("calibrated", [False, True])
def test_linearize_is_the_robust_normal_equations(calibrated: bool) -> None:
    X_k, X_f, T = _problem(2)
    rng = np.random.default_rng(3)
    T1 = sim3.retract(T, rng.normal(0, 0.01, 7))
    Q = rng.uniform(1.0, 4.0, H * W)
    valid = rng.random(H * W) < 0.8
    cfg = TrackingConfig()
    Kc = K if calibrated else None
    Hm, g, cost = tracking.linearize(T1, X_f, X_k, Q, valid, cfg, Kc)
    assert Hm.shape == (7, 7) and g.shape == (7,)
    np.testing.assert_allclose(Hm, Hm.T, rtol=F64_IDENTITY)
    assert np.linalg.eigvalsh(Hm).min() > 0
    # explicit formulation
    if calibrated:
        from mslam_ref.calib import calib_residual_and_jacobian

        r, J, v2 = calib_residual_and_jacobian(T1, X_f, X_k, K, cfg)
        si = (np.sqrt(Q) * valid * v2)[:, None] / np.array([1.0, 1.0, 10.0])
    else:
        r, J = tracking.ray_dist_residual_and_jacobian(T1, X_f, X_k)
        si = (np.sqrt(Q) * valid)[:, None] / np.array([0.003] * 3 + [10.0])
    wr = np.abs(si * r)
    a = si * np.sqrt(np.where(wr < 1.345, 1.0, 1.345 / np.maximum(wr, 1e-300)))
    A = (a[..., None] * J).reshape(-1, 7)
    b = (a * r).ravel()
    np.testing.assert_allclose(Hm, A.T @ A, rtol=F64_SERIES)
    np.testing.assert_allclose(g, -A.T @ b, rtol=F64_SERIES, atol=F64_SOLVE)
    assert cost == pytest.approx(0.5 * b @ b, rel=1e-12)


def test_gradient_of_the_cost_without_huber() -> None:
    """With Huber inactive, g = -d(cost)/dxi (cost = 1/2 sum sqrt_info^2 r^2)."""
    X_k, X_f, T = _problem(4)
    T1 = sim3.retract(T, np.full(7, 1e-4))
    Q, valid = np.full(H * W, 2.0), np.ones(H * W, bool)
    cfg = TrackingConfig(huber=1e9)
    _, g, _ = tracking.linearize(T1, X_f, X_k, Q, valid, cfg)
    cost = lambda TT: np.array([tracking.linearize(TT, X_f, X_k, Q, valid, cfg)[2]])
    np.testing.assert_allclose(-_fd(cost, T1, 1e-7)[0], g, rtol=FD_LOOSE, atol=FD_COST_GRADIENT)


@pytest.mark.parametrize("calibrated", [False, True])
def test_solve_recovers_a_similarity_with_noise_and_outliers(calibrated: bool) -> None:
    X_k, X_f, T = _problem(5, noise=0.002, outliers=0.04)
    Q = np.full(H * W, 2.0)
    valid = np.ones(H * W, bool)
    T_est, info = tracking.solve(
        X_f, X_k, Q, valid, sim3.identity(), TrackingConfig(), K if calibrated else None
    )
    assert not info.failed and info.converged and info.iterations <= 50
    assert info.costs[0] > info.cost
    err = sim3.log(sim3.mul(T_est, sim3.inv(T)))
    assert np.linalg.norm(err[3:6]) < 1e-3  # rotation, rad
    assert abs(err[6]) < 1e-2  # log-scale
    assert np.linalg.norm(sim3.act(T_est, X_f[:1]) - sim3.act(T, X_f[:1])) < 0.02


def test_solve_exact_data_from_truth_stops_at_step_zero() -> None:
    X_k, X_f, T = _problem(6)
    T_est, info = tracking.solve(X_f, X_k, np.full(H * W, 2.0), np.ones(H * W, bool), T)
    assert info.iterations == 1 and info.converged and not info.failed
    np.testing.assert_allclose(T_est, T, atol=F64_SOLVE)


def test_cholesky_failure_reports_failed_and_keeps_the_pose() -> None:
    X_k, X_f, T = _problem(7)
    T0 = sim3.retract(T, np.full(7, 0.01))
    T_est, info = tracking.solve(X_f, X_k, np.full(H * W, 2.0), np.zeros(H * W, bool), T0)
    assert info.failed and not info.converged and info.iterations == 1
    np.testing.assert_array_equal(T_est, T0)


def test_driver_stopping_rules() -> None:
    """Pre-update costs: rel test only from step 1; |tau| test at any step; max_iters."""

    def fake(costs, step):
        it = iter(costs)
        return lambda *a: (np.eye(7), np.full(7, step), next(it))

    args = (np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1), np.ones(1, bool), sim3.identity())
    cfg = TrackingConfig(max_iters=5)
    # relative decrease 1e-4 < 1e-3 between costs 2 and 3 -> stops after 3 linearisations
    _, info = tracking.solve_with(fake([10.0, 5.0, 5.0005, 1.0, 1.0], 0.1), *args, cfg, None)
    assert info.iterations == 3 and info.converged
    # the first cost can never trigger the relative test; a small step does
    _, info = tracking.solve_with(fake([10.0] * 5, 1e-4), *args, cfg, None)
    assert info.iterations == 1 and info.converged
    _, info = tracking.solve_with(fake([10.0, 1.0, 0.1, 0.01, 0.001], 0.1), *args, cfg, None)
    assert info.iterations == 5 and not info.converged
    _, info = tracking.solve_with(fake([0.0, 0.0, 1.0], 0.1), *args, cfg, None)
    assert info.iterations == 2 and info.converged  # 0/0 handled as converged


def test_match_quality_and_masks() -> None:
    Q_ff = np.array([1.0, 4.0, 9.0])
    Q_kf = np.array([4.0, 1.0, 1.0, 16.0])
    idx = np.array([1, 0, 2, 2])
    np.testing.assert_allclose(tracking.match_quality(Q_ff, Q_kf, idx), [4.0, 1.0, 3.0, 12.0])
    vm = np.array([True, True, False, True])
    C_f = np.array([1.0, 1.0, 1.0, 0.0])
    C_k = np.ones(4)
    Q_k = np.array([4.0, 1.0, 3.0, 12.0])
    vo, vk = tracking.tracking_masks(vm, C_f, C_k, Q_k, TrackingConfig())
    assert vo.tolist() == [True, False, False, False]
    assert vk.tolist() == [True, False, False, True]
    assert tracking.match_fraction(vo) == 0.25
    with pytest.raises(ValueError, match="idx_f2k"):
        tracking.match_quality(Q_ff, Q_kf, np.array([0, 1, 2, 3]))


def test_needs_new_keyframe_hand_cases() -> None:
    n = 12
    cfg = TrackingConfig()
    idx = np.arange(n)
    ok = np.ones(n, bool)
    assert not tracking.needs_new_keyframe(idx, ok, ok, cfg)
    # many matches but all onto 3 distinct frame pixels: unique frac 3/12 = 0.25 < 0.333
    assert tracking.needs_new_keyframe(np.repeat([0, 1, 2], 4), ok, ok, cfg)
    # 4/12 = 0.3333 >= 0.333 distinct frame pixels: no new keyframe
    assert not tracking.needs_new_keyframe(np.repeat([0, 1, 2, 3], 3), ok, ok, cfg)
    # match fraction 3/12 < 0.333
    vk = np.zeros(n, bool)
    vk[:3] = True
    assert tracking.needs_new_keyframe(idx, ok, vk, cfg)
    # invalid matches do not count as distinct pixels
    vm = np.zeros(n, bool)
    vm[:3] = True
    assert tracking.needs_new_keyframe(idx, vm, ok, cfg)
    # 12 matches into 3 of 4 cells (n_cells): 3/4 distinct, though 3/12 of the pixels
    assert not tracking.needs_new_keyframe(np.repeat([0, 1, 2], 4), ok, ok, cfg, n_cells=4)
    assert tracking.needs_new_keyframe(np.repeat([0, 1, 2], 4), ok, ok, cfg, n_cells=10)
    for bad in (0, n + 1):
        with pytest.raises(ValueError, match="n_cells"):
            tracking.needs_new_keyframe(idx % 4, ok, ok, cfg, n_cells=bad)


def test_keyframe_overlap_is_the_statistic_the_test_compares() -> None:
    n = 12
    idx, ok = np.arange(n), np.ones(n, bool)
    vk = np.zeros(n, bool)
    vk[:6] = True
    assert tracking.keyframe_overlap(idx, ok, ok) == 1.0
    assert tracking.keyframe_overlap(np.repeat([0, 1, 2], 4), ok, ok) == 0.25
    assert tracking.keyframe_overlap(idx, ok, vk) == 0.5  # the match share binds
    assert tracking.keyframe_overlap(np.repeat([0, 1, 2], 4), ok, ok, n_cells=4) == 0.75
    rng = np.random.default_rng(3)
    for _ in range(50):
        i, m, v = rng.integers(0, n, n), rng.random(n) < 0.7, rng.random(n) < 0.8
        thresh = float(rng.random())
        got = tracking.needs_new_keyframe(i, m, v, TrackingConfig(match_frac_thresh=thresh))
        assert got == (tracking.keyframe_overlap(i, m, v) < thresh)


def test_bad_inputs() -> None:
    X_k, X_f, T = _problem(8)
    Q, v = np.full(H * W, 2.0), np.ones(H * W, bool)
    with pytest.raises(ValueError, match="X_k"):
        tracking.linearize(T, X_f, X_k.reshape(-1, 3), Q, v, TrackingConfig(), K)
    with pytest.raises(ValueError, match="Q"):
        tracking.linearize(T, X_f, X_k, -Q, v)
    with pytest.raises(ValueError, match="valid"):
        tracking.linearize(T, X_f, X_k, Q, v[:-1])
    with pytest.raises(ValueError, match="X_f"):
        tracking.solve(X_f[:-1], X_k, Q, v, T)
    with pytest.raises(ValueError, match="T_CkCf_init"):
        tracking.solve(X_f, X_k, Q, v, np.zeros(8))
