"""Dense-map metrics (``mslam.map_metrics``) on surfaces with known distances."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_CONDITIONED, MAP_ATOL

from mslam import map_metrics as mm
from mslam.datasets.synthetic import make_sequence
from mslam_ref import sim3

#: Sampling step (m) of the synthetic surfaces.
STEP = 0.02


def _plane(size: float = 1.0) -> np.ndarray:
    """(n, 3) grid on the plane z = 0, ``size`` x ``size`` metres, spacing STEP."""
    g = np.arange(0.0, size + 1e-9, STEP)
    x, y = np.meshgrid(g, g, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def _box() -> np.ndarray:
    """(n, 3) the six faces of the unit cube, spacing STEP (a non-planar surface)."""
    P = _plane()
    faces = []
    for axis in range(3):
        for c in (0.0, 1.0):
            F = np.roll(P, axis + 1, axis=1)  # z=0 plane -> the plane x_axis = 0
            F[:, axis] = c
            faces.append(F)
    return np.unique(np.concatenate(faces), axis=0)


def test_identical_clouds_score_zero() -> None:
    P = _box()
    m = mm.map_metrics(P, P)
    assert (m.accuracy, m.completion, m.chamfer, m.far) == (0.0, 0.0, 0.0, 0.0)
    assert m.n_map == m.n_truth == len(P)


def test_offset_plane_gives_the_offset() -> None:
    truth = _plane()
    m = mm.map_metrics(truth + np.array([0.0, 0.0, 0.03]), truth)
    for v in (m.accuracy, m.completion, m.chamfer, m.accuracy_median, m.completion_median):
        assert v == pytest.approx(0.03, abs=MAP_ATOL)
    assert m.accuracy_rmse == pytest.approx(0.03, abs=MAP_ATOL) and m.far == 0.0


def test_far_points_are_counted_and_not_capped() -> None:
    truth = _plane()
    stray = truth[:100] + np.array([0.0, 0.0, 2.0])  # 2 m above the plane
    m = mm.map_metrics(np.concatenate([truth, stray]), truth)
    share = 100 / (len(truth) + 100)
    assert m.far == pytest.approx(share)
    assert m.accuracy == pytest.approx(2.0 * share, abs=MAP_ATOL)  # the mean is not capped
    assert m.accuracy_rmse == pytest.approx(np.sqrt(share) * mm.FAR_DIST, abs=MAP_ATOL)
    assert m.completion == 0.0 and m.accuracy_median == 0.0


def test_half_a_map_is_accurate_but_incomplete() -> None:
    truth = _plane()
    half = truth[truth[:, 0] < 0.5]
    m = mm.map_metrics(half, truth)
    assert m.accuracy == 0.0
    # Truth points at x >= 0.5 are x - 0.48 from the map: mean over the grid ~0.26 / 2.
    missing = truth[truth[:, 0] >= 0.5]
    expected = np.sum(missing[:, 0] - half[:, 0].max()) / len(truth)
    assert m.completion == pytest.approx(expected, abs=MAP_ATOL) and m.completion > 0.1
    assert m.chamfer == pytest.approx(m.completion / 2, abs=MAP_ATOL)


def test_sampling_is_seeded() -> None:
    rng = np.random.default_rng(1)
    truth = _box()
    est = truth + rng.normal(0, 0.01, truth.shape)
    a = mm.map_metrics(est, truth, max_points=500, seed=3)
    b = mm.map_metrics(est, truth, max_points=500, seed=3)
    full = mm.map_metrics(est, truth)
    assert a == b
    assert a.accuracy != full.accuracy and abs(a.accuracy - full.accuracy) < 0.2 * full.accuracy


def test_voxel_downsample_keeps_one_centroid_per_voxel() -> None:
    P = np.array([[0.001, 0.002, 0.003], [0.009, 0.008, 0.007], [0.015, 0.0, 0.0]])
    V = mm.voxel_downsample(P, 0.01)
    np.testing.assert_allclose(V, [[0.005, 0.005, 0.005], [0.015, 0.0, 0.0]], atol=MAP_ATOL)
    assert len(mm.voxel_downsample(_plane(), 0.1)) == 11 * 11


def test_sim3_moved_map_and_trajectory_recover_zero() -> None:
    truth = _box()
    n = 20
    xi = np.zeros((n, 7))
    xi[:, 0] = np.linspace(0, 1, n)
    xi[:, 1] = np.sin(np.linspace(0, 3, n))
    xi[:, 2] = 0.3 * np.cos(np.linspace(0, 2, n))
    gt = sim3.exp(xi)
    G = sim3.exp(np.array([0.5, -2.0, 1.0, 0.4, -0.2, 0.3, np.log(0.5)]))
    est = sim3.mul(G[None], gt)
    stamps = np.arange(n) / 30.0
    m, res, info = mm.evaluate_map(sim3.act(G, truth), stamps, est, stamps, gt, truth)
    assert res.scale == pytest.approx(2.0) and info["scale"] == pytest.approx(2.0)
    assert m.accuracy < MAP_ATOL and m.completion < MAP_ATOL
    assert info["rotation_vs_orientations_deg"] < 1e-6
    m_se3, _, _ = mm.evaluate_map(sim3.act(G, truth), stamps, est, stamps, gt, truth, "se3")
    assert m_se3.accuracy > 0.1  # without the scale the map stays half size


def _line_trajectory(n: int = 20) -> np.ndarray:
    """(n, 8) cameras on a gentle arc in the z = 0 plane, all looking the same way."""
    xi = np.zeros((n, 7))
    xi[:, 0] = np.linspace(0, 1, n)
    xi[:, 1] = 0.1 * np.sin(np.linspace(0, np.pi, n))
    return sim3.exp(xi)


def test_icp_recovers_a_map_the_trajectory_cannot_place() -> None:
    truth = _box()
    gt = _line_trajectory()
    # The estimate's map and orientations are turned 5 degrees, its positions are not: the
    # position fit cannot see the turn, the orientations and ICP can.
    turn = sim3.exp(np.array([0, 0, 0, np.radians(5.0), 0, 0, 0]))
    est = sim3.mul(turn[None], gt)
    est[:, :3] = gt[:, :3]
    est_map = sim3.act(turn, truth)
    stamps = np.arange(len(gt)) / 30.0
    m, _, info = mm.evaluate_map(est_map, stamps, est, stamps, gt, truth)
    assert m.accuracy > 0.01 and info["rotation_vs_orientations_deg"] == pytest.approx(5.0)
    m_icp, res, info = mm.evaluate_map(est_map, stamps, est, stamps, gt, truth, refine="icp")
    assert m_icp.accuracy < 1e-6 and m_icp.completion < 1e-6
    assert info["icp_rotation_deg"] == pytest.approx(5.0, abs=1e-4)
    assert res.rmse < MAP_ATOL  # the trajectory's own ATE does not depend on the refinement


def test_truth_from_rgbd_lies_on_the_rendered_surfaces() -> None:
    seq = make_sequence("loop", n_frames=6, width=32, height=24, seed=0)
    truth = mm.truth_from_rgbd(seq, step=5)
    # Frames 0 and 5 only: each frame's own back-projection is within a voxel of the truth.
    for i in (0, 5):
        f = seq[i]
        from mslam_ref.pointmap import camera_rays

        X = sim3.act(f.T_WC, (f.depth[..., None] * camera_rays(seq.K, *f.shape))[f.depth > 0])
        m = mm.map_metrics(X, truth)
        assert m.accuracy_median < mm.VOXEL
    only_first = mm.truth_from_rgbd(seq, step=5, t_range=(seq.timestamps[0], seq.timestamps[0]))
    assert 0 < len(only_first) < len(truth)


def test_bad_input_raises() -> None:
    P = _plane()
    with pytest.raises(ValueError, match="map_points"):
        mm.map_metrics(np.zeros((0, 3)), P)
    with pytest.raises(ValueError, match="truth_points"):
        mm.map_metrics(P, np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="max_points"):
        mm.map_metrics(P, P, max_points=0)
    with pytest.raises(ValueError, match="voxel"):
        mm.voxel_downsample(P, 0.0)
    with pytest.raises(ValueError, match="ICP"):
        mm.icp_refine(P, P + 10.0, np.eye(3), np.zeros(3), 1.0)
    t = np.arange(20) / 30.0
    with pytest.raises(ValueError, match="refine"):
        mm.evaluate_map(P, t, _line_trajectory(), t, _line_trajectory(), P, refine="nope")


def test_pose_alignment_pins_the_rotation_about_a_straight_path() -> None:
    """Cameras on a nearly straight line: positions leave the roll about the line free, the
    cameras' axes fix it; an exact Sim(3) copy of the cameras is recovered."""
    from mslam.map_metrics import pose_alignment
    from mslam_ref import so3

    rng = np.random.default_rng(3)
    n = 40
    P_gt = np.stack([np.linspace(0, 1, n), 1e-3 * rng.normal(size=n), 1e-3 * rng.normal(size=n)], 1)
    q_gt = so3.exp(0.3 * rng.normal(size=(n, 3)))
    R_true = so3.to_matrix(so3.exp(np.array([0.9, -0.2, 0.4])))
    s_true, t_true = 2.5, np.array([0.3, -1.0, 2.0])
    # the estimate is the truth moved by the inverse similarity
    P_est = ((P_gt - t_true) @ R_true) / s_true
    q_est = so3.from_matrix(R_true.T @ so3.to_matrix(q_gt))
    R, t, s = pose_alignment(P_est, q_est, P_gt, q_gt, s_true)
    np.testing.assert_allclose(R, R_true, atol=F64_CONDITIONED)
    np.testing.assert_allclose([s, *t], [s_true, *t_true], atol=F64_CONDITIONED)
