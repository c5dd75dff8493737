"""Backend (mslam_ref.backend): per-block residuals and Jacobians, the 14x14 blocks, sparse
assembly, and the global Gauss-Newton on a synthetic loop of 10 keyframes."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from tolerances import F64_CONDITIONED, F64_COPY, F64_SERIES, FD_LOOSE, FD_SCALED

from mslam.datasets.synthetic import make_sequence
from mslam_ref import backend, normal_equations, sim3
from mslam_ref.backend import BackendConfig
from mslam_ref.pointmap import backproject

N_KF, W, H = 10, 64, 48


@functools.cache
def loop_graph(n: int = N_KF, width: int = W, height: int = H, seed: int = 0):
    """Keyframes on the synthetic ``loop`` path: exact depth pointmaps, directed blocks for
    every ordered pair with > 20 % of pixels matched by projection (nearest pixel, depth
    consistent within 5 %). Returns T_WC, X, C, ii, jj, idx, valid, K."""
    seq = make_sequence("loop", n_frames=n, width=width, height=height, seed=seed)
    K, T = seq.K, seq.T_WC.copy()
    D = np.stack([seq[i].depth for i in range(n)])
    X = np.stack([backproject(D[i], K) for i in range(n)])
    ii, jj, idx, valid = [], [], [], []
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            P = sim3.act(sim3.mul(sim3.inv(T[i]), T[j]), X[j].reshape(-1, 3))
            z = P[:, 2]
            zs = np.where(z > 1e-6, z, 1.0)
            u = np.rint(K[0, 0] * P[:, 0] / zs + K[0, 2]).astype(np.int64)
            v = np.rint(K[1, 1] * P[:, 1] / zs + K[1, 2]).astype(np.int64)
            ok = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
            m = np.where(ok, u + width * v, 0)
            ok &= np.abs(D[i].reshape(-1)[m] - z) < 0.05 * z
            if ok.mean() > 0.2:
                ii.append(i), jj.append(j), idx.append(m), valid.append(ok)
    C = np.ones(X.shape[:3])
    return T, X, C, np.array(ii), np.array(jj), np.array(idx), np.array(valid), K


def exact_pointmaps(T, X, ii, jj, idx, valid):
    """Make every match exact: all (keyframe, pixel) nodes linked by matches get one world
    point (that of the component's first node), expressed in each keyframe's camera.
    The residuals of the ray + distance error then vanish at the true poses."""
    n, h, w, _ = X.shape
    N = h * w
    rows = (ii[:, None] * N + idx)[valid]
    cols = (jj[:, None] * N + np.arange(N))[valid]
    G = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n * N, n * N))
    nc, lab = connected_components(G, directed=False)
    first = np.empty(nc, np.int64)
    order = np.arange(n * N)[::-1]
    first[lab[order]] = order
    Xw = sim3.act(np.repeat(T, N, 0), X.reshape(-1, 3))[first[lab]]
    return sim3.act(np.repeat(sim3.inv(T), N, 0), Xw).reshape(X.shape)


def _perturb(T, scale, seed):
    rng = np.random.default_rng(seed)
    xi = np.concatenate(
        [rng.normal(0, scale, (len(T), 6)), rng.normal(0, scale / 2, (len(T), 1))], 1
    )
    xi[0] = 0.0
    return sim3.retract(T, xi)


def _traj_err(Ta, T):
    e = sim3.log(sim3.mul(Ta, sim3.inv(T)))
    return float(np.sqrt((e**2).sum(1).mean()))


def test_config_defaults() -> None:
    c = BackendConfig()
    assert (c.pin, c.C_conf, c.Q_conf, c.min_match_frac, c.max_iters) == (1, 0.0, 1.5, 0.1, 10)
    assert (c.pixel_border, c.depth_eps, c.delta_norm) == (-10, 1e-6, 1e-8)
    assert (c.sigma_ray, c.sigma_dist, c.sigma_pixel, c.sigma_depth, c.sigma_point) == (
        0.003,
        10.0,
        1.0,
        10.0,
        0.05,
    )


@pytest.mark.parametrize("calibrated", [False, True])
def test_block_jacobians_match_finite_differences(calibrated: bool) -> None:
    T, X, C, ii, jj, idx, valid, K = loop_graph()
    d = 0
    i, j = ii[d], jj[d]
    Kc = K if calibrated else None
    Ti, Tj = _perturb(T, 0.01, 3)[[i, j]] if i else (T[i], _perturb(T, 0.01, 3)[j])
    Q = np.full(H * W, 2.0)
    args = lambda a, b: (a, b, X[i], X[j], C[i], C[j], idx[d], valid[d], Q, BackendConfig(), Kc)
    e, J_i, J_j, w = backend.block_residual_and_jacobian(*args(Ti, Tj))
    c = 3 if calibrated else 4
    assert e.shape == (H * W, c) and J_i.shape == J_j.shape == (H * W, c, 7)
    np.testing.assert_array_equal(J_i, -J_j)
    on = w[:, 0] > 0
    assert on.sum() > 0.2 * H * W
    eps = 1e-6
    for k in range(7):
        dx = np.zeros(7)
        dx[k] = eps
        fd_i = (
            backend.block_residual_and_jacobian(*args(sim3.retract(Ti, dx), Tj))[0]
            - backend.block_residual_and_jacobian(*args(sim3.retract(Ti, -dx), Tj))[0]
        ) / (2 * eps)
        fd_j = (
            backend.block_residual_and_jacobian(*args(Ti, sim3.retract(Tj, dx)))[0]
            - backend.block_residual_and_jacobian(*args(Ti, sim3.retract(Tj, -dx)))[0]
        ) / (2 * eps)
        scale = 1.0 if calibrated else 0.01  # rays are O(1e-2) per unit step
        np.testing.assert_allclose(J_i[on, :, k], fd_i[on], atol=FD_SCALED * scale, rtol=FD_LOOSE)
        np.testing.assert_allclose(J_j[on, :, k], fd_j[on], atol=FD_SCALED * scale, rtol=FD_LOOSE)


def test_linearize_block_structure_and_zero_residual_at_truth() -> None:
    T, X, C, ii, jj, idx, valid, _ = loop_graph()
    Xe = exact_pointmaps(T, X, ii, jj, idx, valid)
    Q = np.full(valid.shape, 2.0)
    Hs, gs, _ = backend.linearize(
        T, backend.pose_graph(Xe, C, ii[:3], jj[:3], idx[:3], valid[:3], Q[:3])
    )
    assert Hs.shape == (3, 4, 7, 7) and gs.shape == (3, 2, 7)
    np.testing.assert_allclose(Hs[:, 2], np.swapaxes(Hs[:, 1], 1, 2))
    np.testing.assert_allclose(Hs[:, 0], Hs[:, 3])  # J_i = -J_j
    np.testing.assert_allclose(Hs[:, 1], -Hs[:, 3])
    assert np.abs(gs).max() < 1e-6 * np.abs(Hs).max()  # zero residual at the truth
    _, _, cost = backend.linearize(T, backend.pose_graph(Xe, C, ii, jj, idx, valid, Q))
    assert cost < 1e-12
    # one block against its definition
    e, J_i, J_j, w = backend.block_residual_and_jacobian(
        T[ii[0]], T[jj[0]], X[ii[0]], X[jj[0]], C[ii[0]], C[jj[0]], idx[0], valid[0], Q[0]
    )
    Hs1, gs1, _ = backend.linearize(
        T, backend.pose_graph(X, C, ii[:1], jj[:1], idx[:1], valid[:1], Q[:1])
    )
    Wc = np.where(np.abs(w * e) < 1.345, 1.0, 1.345 / np.maximum(np.abs(w * e), 1e-300)) * w * w
    np.testing.assert_allclose(
        Hs1[0, 1], np.einsum("nc,nca,ncb->ab", Wc, J_i, J_j), rtol=F64_SERIES
    )
    np.testing.assert_allclose(
        gs1[0, 1], np.einsum("nc,nc,nca->a", Wc, e, J_j), rtol=F64_SERIES, atol=F64_CONDITIONED
    )


def test_assemble_system_sums_blocks_and_skips_fixed() -> None:
    rng = np.random.default_rng(0)
    Hs, gs = rng.normal(size=(3, 4, 7, 7)), rng.normal(size=(3, 2, 7))
    pos_i, pos_j = np.array([-1, 0, 1]), np.array([0, 1, 0])
    A, b = normal_equations.assemble_system(Hs, gs, pos_i, pos_j, 2)
    Ad, bd = np.zeros((14, 14)), np.zeros(14)
    for d in range(3):
        for k, (p, q) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            a, c = (pos_i[d], pos_j[d])[p], (pos_i[d], pos_j[d])[q]
            if a >= 0 and c >= 0:
                Ad[7 * a : 7 * a + 7, 7 * c : 7 * c + 7] += Hs[d, k]
        for s, a in enumerate((pos_i[d], pos_j[d])):
            if a >= 0:
                bd[7 * a : 7 * a + 7] += gs[d, s]
    np.testing.assert_allclose(A.toarray(), Ad)
    np.testing.assert_allclose(b, bd)


def test_directed_blocks() -> None:
    a = lambda v: np.full((1, 4), v)
    ii, jj, idx, valid, Q = backend.directed_blocks(
        [2], [5], a(1), a(2), a(True), a(False), a(3.0), a(4.0)
    )
    assert ii.tolist() == [2, 5] and jj.tolist() == [5, 2]
    assert (
        idx[:, 0].tolist() == [1, 2]
        and valid[:, 0].tolist() == [True, False]
        and Q[:, 0].tolist() == [3.0, 4.0]
    )


def test_solve_exact_loop_recovers_the_trajectory() -> None:
    T, X, _, ii, jj, idx, valid, _ = loop_graph()
    Xe = exact_pointmaps(T, X, ii, jj, idx, valid)
    # an 11th keyframe outside the graph keeps its pose
    T_all = np.concatenate([T, sim3.exp(np.full((1, 7), 0.1))])
    X_all = np.concatenate([Xe, Xe[:1]])
    C_all = np.ones(X_all.shape[:3])
    T0 = _perturb(T_all, 0.03, 1)
    graph = backend.pose_graph(X_all, C_all, ii, jj, idx, valid, np.full(valid.shape, 2.0))
    T1, info = backend.solve(T0, graph)
    e0, e1 = _traj_err(T0[:N_KF], T), _traj_err(T1[:N_KF], T)
    assert e0 > 0.03 and e1 < e0 / 10 and e1 < 1e-6
    np.testing.assert_array_equal(T1[0], T0[0])  # gauge: the first keyframe never moves
    np.testing.assert_array_equal(T1[N_KF], T0[N_KF])
    assert info.keyframes == tuple(range(N_KF)) and info.failed == 0
    assert info.iterations == len(info.costs) == len(info.step_norms) <= 10
    assert info.costs[-1] < 1e-6 * info.costs[0]


def test_solve_calibrated_loop_reduces_the_error_tenfold() -> None:
    T, X, C, ii, jj, idx, valid, K = loop_graph()
    T0 = _perturb(T, 0.1, 2)
    graph = backend.pose_graph(X, C, ii, jj, idx, valid, np.full(valid.shape, 2.0), K)
    T1, info = backend.solve(T0, graph, BackendConfig())
    assert _traj_err(T1, T) < _traj_err(T0, T) / 10  # limited by the pixel quantisation of matches
    np.testing.assert_array_equal(T1[0], T0[0])
    assert info.iterations <= 10 and info.costs[-1] < info.costs[0]


def test_solve_edge_cases() -> None:
    T, X, C, ii, jj, idx, valid, _ = loop_graph()
    Q = np.full(valid.shape, 2.0)
    T0 = _perturb(T, 0.01, 4)
    # pin >= number of keyframes in the graph: nothing to do
    one_edge = backend.pose_graph(X, C, ii[:1], jj[:1], idx[:1], valid[:1], Q[:1])
    T1, info = backend.solve(T0, one_edge, BackendConfig(pin=2))
    assert info.iterations == 0
    np.testing.assert_array_equal(T1, T0)
    # no valid pixel: the factorisation fails, the step is zero (upstream), so |dx| = 0 stops
    no_valid = backend.pose_graph(X, C, ii, jj, idx, np.zeros_like(valid), Q)
    T1, info = backend.solve(T0, no_valid, BackendConfig(max_iters=2))
    assert info.failed == 1 and info.iterations == 1 and info.step_norms == (0.0,)
    np.testing.assert_allclose(T1, T0, atol=F64_COPY)
    # pin = 2 keeps the first two sorted keyframes fixed
    graph = backend.pose_graph(X, C, ii, jj, idx, valid, Q)
    T1, _ = backend.solve(T0, graph, BackendConfig(pin=2, max_iters=1))
    np.testing.assert_array_equal(T1[:2], T0[:2])
    assert np.abs(T1[2:] - T0[2:]).max() > 0


def test_bad_inputs() -> None:
    T, X, C, ii, jj, idx, valid, _ = loop_graph()
    Q = np.full(valid.shape, 2.0)
    with pytest.raises(ValueError, match="ii"):
        backend.pose_graph(X, C, ii + 100, jj, idx, valid, Q)
    with pytest.raises(ValueError, match="idx"):
        backend.pose_graph(X, C, ii, jj, idx[:, :-1], valid, Q)
    with pytest.raises(ValueError, match="C"):
        backend.pose_graph(X, C[:, :-1], ii, jj, idx, valid, Q)
    with pytest.raises(ValueError, match="T_WC"):
        backend.solve(T[:, :7], backend.pose_graph(X, C, ii, jj, idx, valid, Q))
