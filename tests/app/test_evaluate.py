"""ATE (evo-compatible association + Umeyama) and reconstruction metrics (mslam.evaluate).

The evo rows are the reference numbers of the data folder's traj/SOURCES.md (evo 1.38.1),
rounded there to 6 decimals; every one is reproduced to 1e-6.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from tolerances import F64_CONDITIONED, F64_IDENTITY, TEXT_6_DECIMALS

from mslam import evaluate as ev
from mslam import formats as io
from mslam_ref import sim3

# (ground truth, estimate, align, matched, n_est, scale or None, rmse, mean, median, max)
EVO_ROWS = [
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "none",
     785, 788, None, 0.020079, 0.018063, 0.016518, 0.043289),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "se3",
     785, 788, 1.0, 0.013470, 0.012024, 0.011183, 0.034760),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "sim3",
     785, 788, 1.008001, 0.013389, 0.011987, 0.011134, 0.034846),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-ORB_kf_mono.txt", "sim3",
     32, 32, 1.105622, 0.009755, 0.008219, 0.007909, 0.027924),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", "se3",
     2174, 2893, 1.0, 0.008119, 0.007492, 0.007415, 0.024300),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", "sim3",
     2174, 2893, 0.996970, 0.006123, 0.005586, 0.005305, 0.021477),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB_kf_mono.txt", "sim3",
     118, 157, 2.228022, 0.007729, 0.007104, 0.007100, 0.015689),
    ("V101_gt.txt", "V101_openvins.txt", "se3",
     2760, 2776, 1.0, 0.052102, 0.047083, 0.042658, 0.124886),
    ("V101_gt.txt", "V101_openvins.txt", "sim3",
     2760, 2776, 1.004098, 0.051553, 0.045268, 0.041006, 0.131205),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "se3",
     4541, 4541, 1.0, 1.303450, 1.156997, 1.065625, 3.587949),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "sim3",
     4541, 4541, None, 0.937709, 0.872693, 0.844691, 2.693500),
    ("KITTI_00_gt.txt", "KITTI_00_SPTAM.txt", "se3",
     4541, 4541, 1.0, 3.738488, 3.490977, 3.642585, 7.768977),
]  # fmt: skip


def _check_row(res: ev.AteResult, matched, n_est, scale, rmse, mean, median, mx) -> None:
    assert (res.matched, res.n_est) == (matched, n_est)
    if scale is not None:
        assert res.scale == pytest.approx(scale, abs=1e-6)
    got = (res.rmse, res.mean, res.median, res.max)
    np.testing.assert_allclose(got, (rmse, mean, median, mx), rtol=0, atol=TEXT_6_DECIMALS)


@pytest.mark.parametrize("row", EVO_ROWS, ids=lambda r: f"{r[1]}-{r[2]}")
def test_reproduces_evo_ape(shared_data, row) -> None:
    gt_name, est_name, align, *expected = row
    d = shared_data / "traj"
    if gt_name.startswith("KITTI"):
        gt, est = io.read_kitti(d / gt_name), io.read_kitti(d / est_name)
        res = ev.ate(None, est, None, gt, align=align)
    else:
        gs, gp = io.read_tum(d / gt_name)
        es, ep = io.read_tum(d / est_name)
        res = ev.ate(es, ep, gs, gp, align=align, max_diff=0.01)
    _check_row(res, *expected)


def test_reproduces_evo_v102_via_euroc_csv_conversion(shared_data, tmp_path) -> None:
    """``evo_traj euroc V102_groundtruth.csv --save_as_tum`` then ``evo_ape tum ... -as``."""
    d = shared_data / "traj"
    gs, gp = io.read_euroc_csv(d / "V102_groundtruth.csv")
    io.write_tum(tmp_path / "V102_gt.tum", gs, gp)
    gs2, gp2 = io.read_tum(tmp_path / "V102_gt.tum")
    np.testing.assert_array_equal(gs2, gs)
    es, ep = io.read_tum(d / "V102.txt")
    res = ev.ate(es, ep, gs2, gp2, align="sim3")
    _check_row(res, 798, 807, 0.979698, 0.083841, 0.074841, 0.071945, 0.226652)
    # The direct csv path gives the same answer.
    assert ev.ate(es, ep, gs, gp).rmse == pytest.approx(res.rmse, abs=1e-12)


def _random_traj(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 8) Sim(3) camera poses along a wiggly 3-D path (unit scale)."""
    xi = np.zeros((n, 7))
    xi[:, :3] = np.cumsum(rng.normal(0, 0.3, (n, 3)), axis=0)
    xi[:, 3:6] = rng.normal(0, 0.5, (n, 3))
    T = sim3.exp(xi)
    T[:, :3] = xi[:, :3]
    T[:, 7] = 1.0
    return T


@given(
    seed=st.integers(0, 10_000),
    log_s=st.floats(-2.0, 2.0),
    align=st.sampled_from(["sim3", "se3"]),
)
def test_transformed_gt_gives_zero_ate_and_recovers_scale(seed, log_s, align) -> None:
    rng = np.random.default_rng(seed)
    n = 30
    gt = _random_traj(rng, n)
    stamps = np.cumsum(rng.uniform(0.02, 0.1, n))
    s = float(np.exp(log_s)) if align == "sim3" else 1.0
    G = sim3.exp(np.concatenate([rng.normal(0, 2, 6), [np.log(s)]]))
    est = sim3.mul(G[None], gt)  # est = G · gt: a Sim(3) transform of the whole trajectory
    res = ev.ate(stamps, est, stamps, gt, align=align)
    assert res.matched == n and res.n_est == n
    assert res.rmse < 1e-9 * max(1.0, 1.0 / s)
    assert res.scale == pytest.approx(1.0 / s, rel=1e-9)
    np.testing.assert_allclose(res.aligned_positions, gt[:, :3], atol=F64_CONDITIONED)


def test_se3_alignment_cannot_absorb_scale_but_sim3_can() -> None:
    rng = np.random.default_rng(3)
    gt = _random_traj(rng, 40)
    est = gt.copy()
    est[:, :3] *= 0.5
    t = np.arange(40) * 0.1
    assert ev.ate(t, est, t, gt, align="sim3").rmse < 1e-12
    assert ev.ate(t, est, t, gt, align="se3").rmse > 0.1
    assert ev.ate(t, est, t, gt, align="none").rmse > 0.1


def test_no_alignment_is_plain_distance() -> None:
    gt = np.zeros((4, 3))
    est = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0], [0, 0, 3.0]])
    t = np.arange(4.0)
    res = ev.ate(t, est, t, gt, align="none")
    assert (res.scale, res.max, res.median, res.mean) == (1.0, 3.0, 1.5, 1.5)
    assert res.rmse == pytest.approx(np.sqrt(14 / 4))


def test_umeyama_reflection_case_gives_a_rotation() -> None:
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    dst = src * np.array([1, 1, -1.0])  # a mirror image: best proper rotation, det +1
    R, _, s = ev.umeyama(src, dst, with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=F64_IDENTITY)
    assert 0 < s < 1


def test_umeyama_degenerate_raises() -> None:
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="degenerate"):
        ev.umeyama(line, line + 1.0)
    with pytest.raises(ValueError, match="src"):
        ev.umeyama(np.zeros((3, 2)), np.zeros((3, 2)))


def test_umeyama_refuses_a_static_set_whose_mean_rounds() -> None:
    """A camera that only rotates: 30 equal positions whose mean differs from them by rounding
    (~1e-16). The ground truth has no spread, so no scale or ATE exists; either side static is
    refused, while the same set moving by a micrometre still aligns."""
    static = np.tile([0.3, -0.2, 1.4], (30, 1))
    assert np.any(static.mean(axis=0) != static[0])  # the rounding the check must see through
    moving = np.random.default_rng(0).normal(0.0, 0.1, (30, 3))
    with pytest.raises(ValueError, match="dst: degenerate"):
        ev.umeyama(moving, static)
    with pytest.raises(ValueError, match="src: degenerate"):
        ev.umeyama(static, moving)
    t = np.arange(30) / 30.0
    with pytest.raises(ValueError, match="gt_poses: degenerate"):
        ev.ate(t, moving, t, static, align="sim3")
    with pytest.raises(ValueError, match=r"est_poses: degenerate .* or one that only turned"):
        ev.ate(t, static, t, moving, align="sim3")
    _, _, s = ev.umeyama(moving, static + 1e-6 * moving)
    assert np.isfinite(s) and s > 0


# ---- association (evo's matching_time_indices as driven by associate_trajectories) ----


def test_association_nearest_within_max_diff() -> None:
    gt = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    est = np.array([0.004, 0.109, 0.2101, 0.35])
    i_est, i_gt = ev.associate(est, gt, max_diff=0.01)
    # 0.004 -> 0.0, 0.109 -> 0.1 (9 ms), 0.2101 too far (10.1 ms), 0.35 too far
    np.testing.assert_array_equal(i_est, [0, 1])
    np.testing.assert_array_equal(i_gt, [0, 1])


def test_association_boundary_is_inclusive() -> None:
    gt = np.array([0.0, 1.0])
    est = np.array([0.25, 0.75])  # both exactly 0.25 s (binary-exact) from a GT stamp
    i_est, i_gt = ev.associate(est, gt, max_diff=0.25)
    np.testing.assert_array_equal(i_est, [0, 1])
    np.testing.assert_array_equal(i_gt, [0, 1])


def test_association_tie_takes_first_index_and_reuse_allowed() -> None:
    gt = np.array([0.0, 0.02, 0.04])
    est = np.array([0.01, 0.011])  # 0.01 ties between gt 0 and 1 -> first; both may use gt 1
    i_est, i_gt = ev.associate(est, gt, max_diff=0.01)
    np.testing.assert_array_equal(i_est, [0, 1])
    np.testing.assert_array_equal(i_gt, [0, 1])
    i_est, i_gt = ev.associate(np.array([0.019, 0.021]), gt, max_diff=0.01)
    np.testing.assert_array_equal(i_gt, [1, 1])


def test_association_shorter_trajectory_drives() -> None:
    """With a longer estimate, each GT stamp picks its nearest estimate (evo swaps roles)."""
    gt = np.array([0.0, 1.0])
    est = np.array([0.0, 0.004, 0.008, 0.996, 1.5])
    i_est, i_gt = ev.associate(est, gt, max_diff=0.01)
    np.testing.assert_array_equal(i_gt, [0, 1])
    np.testing.assert_array_equal(i_est, [0, 3])


def test_association_unsorted_and_no_match() -> None:
    gt = np.array([0.3, 0.1, 0.2])
    i_est, i_gt = ev.associate(np.array([0.2, 0.1]), gt)
    np.testing.assert_array_equal(i_gt, [2, 1])
    i_est, i_gt = ev.associate(np.array([5.0]), gt)
    assert i_est.size == 0 and i_gt.size == 0
    with pytest.raises(ValueError, match="no estimate stamp"):
        ev.ate(np.array([5.0, 6.0, 7.0]), np.zeros((3, 3)), gt, np.zeros((3, 3)))


@given(seed=st.integers(0, 10_000), n_est=st.integers(1, 40), n_gt=st.integers(1, 40))
def test_association_matches_naive_loop(seed, n_est, n_gt) -> None:
    rng = np.random.default_rng(seed)
    est = np.round(rng.uniform(0, 1, n_est), 2)  # rounding creates ties and duplicates
    gt = np.round(rng.uniform(0, 1, n_gt), 2)
    short, long = (est, gt) if n_est <= n_gt else (gt, est)
    pairs = []
    for i, a in enumerate(short):
        j = int(np.argmin(np.abs(long - a)))
        if abs(long[j] - a) <= 0.01:
            pairs.append((i, j))
    exp_s = np.array([p[0] for p in pairs], np.int64)
    exp_l = np.array([p[1] for p in pairs], np.int64)
    i_est, i_gt = ev.associate(est, gt, 0.01)
    got_s, got_l = (i_est, i_gt) if n_est <= n_gt else (i_gt, i_est)
    np.testing.assert_array_equal(got_s, exp_s)
    np.testing.assert_array_equal(got_l, exp_l)


def test_ate_input_validation() -> None:
    t = np.arange(5.0)
    p = np.random.default_rng(0).normal(size=(5, 3))
    with pytest.raises(ValueError, match="align"):
        ev.ate(t, p, t, p, align="affine")
    with pytest.raises(ValueError, match="est_poses"):
        ev.ate(t, np.zeros((5, 5)), t, p)
    with pytest.raises(ValueError, match="est_stamps"):
        ev.ate(t[:4], p, t, p)
    with pytest.raises(ValueError, match="equal lengths"):
        ev.ate(None, p[:4], None, p)
    with pytest.raises(ValueError, match="max_diff"):
        ev.ate(t, p, t, p, max_diff=-1.0)
    with pytest.raises(ValueError, match="gt_poses"):
        ev.ate(t, p, t, np.full((5, 3), np.nan))
    res = ev.ate(None, p, None, p)  # index association
    assert res.matched == 5 and res.rmse < 1e-12


def test_ate_accepts_every_pose_layout() -> None:
    rng = np.random.default_rng(1)
    gt = _random_traj(rng, 12)
    t = np.arange(12.0)
    ref = ev.ate(t, gt * [1, 1, 1, 1, 1, 1, 1, 2.0], t, gt).rmse  # scale column ignored
    for est in (gt[:, :3], gt[:, :7], sim3.to_matrix(gt), sim3.to_matrix(gt)[:, :3]):
        assert ev.ate(t, est, t, gt).rmse == pytest.approx(ref, abs=1e-12)


# ---- reconstruction metrics ----


def test_reconstruction_identical_clouds_are_zero() -> None:
    pts = np.random.default_rng(0).uniform(-1, 1, (500, 3))
    assert ev.reconstruction_metrics(pts, pts) == (0.0, 0.0, 0.0)


def test_reconstruction_accuracy_and_completion_directions() -> None:
    ref = np.stack(np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11), [0.0]), -1)
    ref = ref.reshape(-1, 3)
    est = ref[ref[:, 0] <= 0.5] + [0, 0, 0.1]  # half the surface, lifted 10 cm
    acc, comp, cham = ev.reconstruction_metrics(est, ref)
    assert acc == pytest.approx(0.1)  # every estimated point is 0.1 from the reference
    # completion: the covered half is 0.1 away, the other half further (capped at 0.5)
    assert comp > acc and comp <= 0.5
    assert cham == pytest.approx((acc + comp) / 2)


def test_reconstruction_cap_truncates_outliers() -> None:
    ref = np.zeros((1, 3))
    est = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    acc, comp, _ = ev.reconstruction_metrics(est, ref, max_dist=0.5)
    assert acc == pytest.approx(np.sqrt((0 + 0.5**2) / 2))  # truncated, not excluded
    assert comp == 0.0
    acc2, _, _ = ev.reconstruction_metrics(est, ref, max_dist=20.0)
    assert acc2 == pytest.approx(np.sqrt(100 / 2))


def test_reconstruction_validation() -> None:
    p = np.zeros((3, 3))
    with pytest.raises(ValueError, match="est_points"):
        ev.reconstruction_metrics(np.zeros((0, 3)), p)
    with pytest.raises(ValueError, match="ref_points"):
        ev.reconstruction_metrics(p, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="max_dist"):
        ev.reconstruction_metrics(p, p, max_dist=0.0)
