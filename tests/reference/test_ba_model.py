"""BA reference: Jacobians vs finite differences, robust kernels, Schur step vs dense LM step,
monotone cost, fixed vertices."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from tolerances import F64_CONDITIONED, F64_SOLVE, FD_LOOSE, FD_RTOL, SCHUR_VS_DENSE

import mslam_ref.ba as K
from mslam_ref import se3
from mslam_ref.ba import cameras, lm, schur, synthetic
from mslam_ref.ba.cameras import bal_retract_cameras
from mslam_ref.ba.robust import RobustKernel, rho_and_weight


def _fd(f, x0: np.ndarray, retract, dof: int, h: float = 1e-6) -> np.ndarray:
    cols = []
    for e in np.eye(dof):
        cols.append((f(retract(x0, h * e)) - f(retract(x0, -h * e))) / (2 * h))
    return np.stack(cols, -1)


def test_pinhole_jacobians_fd() -> None:
    init, _ = synthetic.make_pinhole_problem(n_cams=3, n_points=5, stereo_fraction=0.5, seed=3)
    p = init
    st = p.is_stereo.astype(float)
    r, Jc, Jp = cameras.pinhole_linearize(
        p.poses, p.intrinsics, p.points, p.obs_cam, p.obs_pt, p.meas, st
    )
    assert st.min() == 0.0 and st.max() == 1.0  # both edge types covered
    for e in range(len(r)):
        c, j = p.obs_cam[e], p.obs_pt[e]

        def res_pose(T, e=e, j=j, c=c):
            return cameras.pinhole_residuals(T[None], p.intrinsics[c][None], p.points[j][None],
                                             [0], [0], p.meas[e][None], st[e][None])[0]  # fmt: skip

        def res_pt(X, e=e, c=c):
            return cameras.pinhole_residuals(p.poses[c][None], p.intrinsics[c][None], X[None],
                                             [0], [0], p.meas[e][None], st[e][None])[0]  # fmt: skip

        np.testing.assert_allclose(
            Jc[e], _fd(res_pose, p.poses[c], se3.retract, 6), rtol=FD_RTOL, atol=FD_LOOSE
        )
        np.testing.assert_allclose(
            Jp[e], _fd(res_pt, p.points[j], np.add, 3), rtol=FD_RTOL, atol=FD_LOOSE
        )
        np.testing.assert_allclose(r[e], res_pose(p.poses[c]))


def test_bal_jacobians_fd() -> None:
    init, _ = synthetic.make_bal_problem(n_cams=3, n_points=5, seed=4)
    p = init
    r, Jc, Jp = cameras.bal_linearize(p.cameras, p.points, p.obs_cam, p.obs_pt, p.obs)
    for e in range(len(r)):
        c, j = p.obs_cam[e], p.obs_pt[e]

        def res_cam(C, e=e, j=j):
            return cameras.bal_residuals(C[None], p.points[j][None], [0], [0], p.obs[e][None])[0]

        def res_pt(X, e=e, c=c):
            return cameras.bal_residuals(p.cameras[c][None], X[None], [0], [0], p.obs[e][None])[0]

        def retr(C, d):
            return bal_retract_cameras(C[None], d[None])[0]

        np.testing.assert_allclose(
            Jc[e], _fd(res_cam, p.cameras[c], retr, 9), rtol=FD_RTOL, atol=FD_LOOSE
        )
        np.testing.assert_allclose(
            Jp[e], _fd(res_pt, p.points[j], np.add, 3), rtol=FD_RTOL, atol=FD_LOOSE
        )


@pytest.mark.parametrize("kind", ["none", "huber", "tukey"])
def test_robust_kernels(kind: str) -> None:
    k = RobustKernel(kind, delta=2.0)
    s = np.array([0.0, 1.0, 3.99, 4.0, 4.01, 9.0, 100.0])
    rho, w = rho_and_weight(s, k)
    h = 1e-6
    rp, _ = rho_and_weight(s + h, k)
    rm, _ = rho_and_weight(np.maximum(s - h, 0.0), k)
    num = (rp - rm) / (s + h - np.maximum(s - h, 0.0))
    np.testing.assert_allclose(w, num, atol=FD_LOOSE)
    np.testing.assert_allclose(
        rho[:2], s[:2] if kind != "tukey" else 4 / 3 * (1 - (1 - s[:2] / 4) ** 3)
    )
    if kind == "huber":
        np.testing.assert_allclose(rho[-1], 2 * 2.0 * 10.0 - 4.0)
        np.testing.assert_allclose(w[-1], 0.2)
    if kind == "tukey":
        assert rho[-1] == pytest.approx(4.0 / 3.0) and w[-1] == 0.0
    with pytest.raises(ValueError, match="kind"):
        RobustKernel("cauchy")
    with pytest.raises(ValueError, match="delta"):
        RobustKernel("huber", -1.0)


def _dense_step(blocks, lam, st):
    U, V, W, bc, bl = blocks
    M, d, P = st.n_cams, st.cam_dof, st.n_points
    H = np.zeros((M * d + 3 * P, M * d + 3 * P))
    for i in range(M):
        H[i * d : (i + 1) * d, i * d : (i + 1) * d] = U[i]
    for j in range(P):
        o = M * d + 3 * j
        H[o : o + 3, o : o + 3] = V[j]
    for e, (i, j) in enumerate(zip(st.obs_cam, st.obs_pt)):
        o = M * d + 3 * j
        H[i * d : (i + 1) * d, o : o + 3] += W[e]
        H[o : o + 3, i * d : (i + 1) * d] += W[e].T
    b = np.r_[bc.ravel(), bl.ravel()]
    x = np.linalg.solve(H + lam * np.eye(len(H)), b)
    return x[: M * d].reshape(M, d), x[M * d :].reshape(P, 3), H, b


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("kind", ["pinhole", "bal"])
def test_schur_step_equals_dense_step(seed: int, kind: str) -> None:
    mk = synthetic.make_pinhole_problem if kind == "pinhole" else synthetic.make_bal_problem
    p, _ = mk(n_cams=4, n_points=12, views=3, seed=seed)
    # duplicate one observation (same camera, same point) to exercise that corner
    r, Jc, Jp = p.linearize(K, *p.params())
    st = schur.build_structure(p.obs_cam, p.obs_pt, len(p.params()[0]), len(p.points), p.cam_dof)
    w = np.random.default_rng(seed).uniform(0.5, 2.0, len(r))
    blocks = schur.normal_blocks(r, Jc, Jp, w, st)
    # the normal-equation blocks equal J^T W J of the assembled Jacobian
    dc_d, dl_d, H, b = _dense_step(blocks, 0.1, st)
    M, d = st.n_cams, st.cam_dof
    J = np.zeros((r.size, M * d + 3 * st.n_points))
    k = r.shape[1]
    for e, (i, j) in enumerate(zip(st.obs_cam, st.obs_pt)):
        J[e * k : (e + 1) * k, i * d : (i + 1) * d] = Jc[e]
        J[e * k : (e + 1) * k, M * d + 3 * j : M * d + 3 * j + 3] = Jp[e]
    ww = np.repeat(w, k)
    np.testing.assert_allclose(H, J.T @ (ww[:, None] * J), atol=F64_CONDITIONED * np.abs(H).max())
    np.testing.assert_allclose(b, -J.T @ (ww * r.ravel()), atol=F64_CONDITIONED * np.abs(b).max())
    dc, dl = lm.solve_damped(blocks, 0.1, st)
    np.testing.assert_allclose(dc, dc_d, rtol=SCHUR_VS_DENSE, atol=F64_SOLVE)
    np.testing.assert_allclose(dl, dl_d, rtol=SCHUR_VS_DENSE, atol=F64_SOLVE)


def test_duplicate_observation_and_sparse_path(monkeypatch: pytest.MonkeyPatch) -> None:
    p, _ = synthetic.make_bal_problem(n_cams=4, n_points=10, seed=5)
    oc, op = np.r_[p.obs_cam, p.obs_cam[0]], np.r_[p.obs_pt, p.obs_pt[0]]
    p = type(p)(p.cameras, p.points, oc, op, np.r_[p.obs, p.obs[:1] + 0.3])
    r, Jc, Jp = p.linearize(K, *p.params())
    st = schur.build_structure(oc, op, 4, 10, 9)
    blocks = schur.normal_blocks(r, Jc, Jp, np.ones(len(r)), st)
    dc_d, dl_d, _, _ = _dense_step(blocks, 0.3, st)
    dc, _ = lm.solve_damped(blocks, 0.3, st)
    np.testing.assert_allclose(dc, dc_d, rtol=SCHUR_VS_DENSE, atol=F64_SOLVE)
    monkeypatch.setattr(schur, "DENSE_MAX", 0)  # sparse LU path
    dc2, dl2 = lm.solve_damped(blocks, 0.3, st)
    np.testing.assert_allclose(dc2, dc_d, rtol=SCHUR_VS_DENSE, atol=F64_SOLVE)
    np.testing.assert_allclose(dl2, dl_d, rtol=SCHUR_VS_DENSE, atol=F64_SOLVE)


@pytest.mark.parametrize("jacobi", [False, True])
def test_cost_never_increases_and_converges(jacobi: bool) -> None:
    p, truth = synthetic.make_pinhole_problem(
        n_cams=5, n_points=30, seed=7, kernel=RobustKernel("huber", np.sqrt(5.991))
    )
    res = lm.optimize(p, lm.LMConfig(iterations=30, jacobi_scaling=jacobi))
    costs = [res.initial_cost] + [h["cost"] for h in res.history]
    assert all(b <= a for a, b in itertools.pairwise(costs))
    assert res.final_cost < 0.01 * res.initial_cost
    assert res.final_cost <= lm.optimize(truth, lm.LMConfig(iterations=0)).final_cost
    assert set(res.profile) == set(lm.PROFILE_KEYS)
    assert res.edge_chi2.shape == (len(p.obs_cam),)


def test_fixed_vertices_never_move() -> None:
    p, _ = synthetic.make_pinhole_problem(n_cams=5, n_points=30, seed=8)
    pose_fixed = np.zeros(5, bool)
    pose_fixed[[0, 2]] = True
    point_fixed = np.zeros(30, bool)
    point_fixed[::4] = True
    q = type(p)(p.poses, p.intrinsics, p.points, p.obs_cam, p.obs_pt, p.meas, p.is_stereo,
                p.information, pose_fixed, point_fixed)  # fmt: skip
    res = lm.optimize(q, lm.LMConfig(iterations=10))
    assert res.final_cost < res.initial_cost
    np.testing.assert_array_equal(res.problem.poses[pose_fixed], q.poses[pose_fixed])
    np.testing.assert_array_equal(res.problem.points[point_fixed], q.points[point_fixed])
    assert not np.allclose(res.problem.poses[~pose_fixed], q.poses[~pose_fixed])
    # everything fixed: no unknowns, nothing moves, no failure
    allfix = type(p)(p.poses, p.intrinsics, p.points, p.obs_cam, p.obs_pt, p.meas,
                     pose_fixed=np.ones(5, bool), point_fixed=np.ones(30, bool))  # fmt: skip
    res2 = lm.optimize(allfix, lm.LMConfig(iterations=3))
    assert res2.final_cost == 0.0 and res2.initial_cost == 0.0  # all edges dropped
    np.testing.assert_array_equal(res2.problem.points, p.points)


def test_problem_validation() -> None:
    p, _ = synthetic.make_bal_problem(n_cams=3, n_points=5)
    with pytest.raises(ValueError, match="obs_cam"):
        type(p)(p.cameras, p.points, p.obs_cam + 10, p.obs_pt, p.obs)
    with pytest.raises(ValueError, match="obs"):
        type(p)(p.cameras, p.points, p.obs_cam, p.obs_pt, p.obs[:-1])
    with pytest.raises(ValueError, match="iterations"):
        lm.LMConfig(iterations=-1)
