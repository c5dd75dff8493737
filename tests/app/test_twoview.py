"""Two-view prior: geometry on synthetic pairs with known pose and depth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tolerances import TRIANGULATION

from mslam.datasets.synthetic import make_sequence
from mslam.priors.base import check_prediction
from mslam.priors.rgbd import FAILED_Q
from mslam.priors.twoview import TwoViewPrior, TwoViewPriorConfig
from mslam.priors.twoview_dis import dense_flow
from mslam.priors.twoview_geometry import (
    essential_pose,
    focal_guess_intrinsics,
    forward_backward_error,
    homography_parallax,
    triangulate_midpoint,
)
from mslam_ref import sim3, so3
from mslam_ref.pointmap import backproject, project

W, H = 128, 96


@pytest.fixture(scope="module")
def seq():
    # The forward path, 40 frames at 128x96: ~8 cm and ~1° between neighbours.
    return make_sequence("forward", n_frames=40, width=W, height=H, seed=0)


def _T_ji(seq, i, j):
    return sim3.mul(sim3.inv(seq[j].T_WC), seq[i].T_WC)


def _rot_err_deg(R, R_gt):
    return np.degrees(np.arccos(np.clip((np.trace(R.T @ R_gt) - 1) / 2, -1, 1)))


def _dir_err_deg(t, t_gt):
    return np.degrees(np.arccos(np.clip(t @ t_gt / np.linalg.norm(t_gt), -1, 1)))


def test_focal_guess_is_a_60_degree_camera():
    K = focal_guess_intrinsics(640, 480)
    assert np.isclose(2 * np.degrees(np.arctan(320 / K[0, 0])), 60.0)
    assert np.allclose(K[:2, 2], [319.5, 239.5])
    with pytest.raises(ValueError, match="width"):
        focal_guess_intrinsics(1, 10)


def test_triangulation_and_essential_pose_are_exact_on_exact_correspondences(seq):
    rng = np.random.default_rng(0)
    T = _T_ji(seq, 0, 2)
    R_gt, t_gt = so3.to_matrix(T[3:7]), T[:3]
    X_i = backproject(seq[0].depth, seq.K).reshape(-1, 3)[rng.choice(W * H, 400)]
    uv_i, _ = project(X_i, seq.K)
    uv_j, _ = project(X_i @ R_gt.T + t_gt, seq.K)
    R, t, inl = essential_pose(uv_i, uv_j, seq.K, ransac_px=0.5)
    assert inl.mean() > 0.95
    assert _rot_err_deg(R, R_gt) < 0.01 and _dir_err_deg(t, t_gt) < 0.1
    s = np.linalg.norm(t_gt)
    X, angle, ok = triangulate_midpoint(uv_i, uv_j, seq.K, R, t * s)
    assert ok.all() and np.all(angle > 0)
    np.testing.assert_allclose(X, X_i, rtol=TRIANGULATION)


def test_flow_forward_backward_is_small_where_both_views_see_the_scene(seq):
    F_ij, F_ji = dense_flow(seq[0].rgb, seq[1].rgb)
    assert F_ij.shape == (H, W, 2)
    e, inside = forward_backward_error(F_ij, F_ji)
    assert np.median(e[inside]) < 0.5
    with pytest.raises(ValueError, match="rgb"):
        dense_flow(seq[0].rgb[..., 0], seq[1].rgb)


@pytest.mark.parametrize("j", [4, 6])
def test_pair_pose_and_depth_up_to_scale(seq, j):
    """Relative pose from the prior's flow + essential matrix, and X_ii, X_ji against truth."""
    prior = TwoViewPrior(seq.K, (W, H))
    fi, fj = seq[0], seq[j]
    p = prior.pair(fi, fj)
    check_prediction(p)
    assert prior.last_status == "ok"
    T = _T_ji(seq, 0, j)
    R_gt = so3.to_matrix(T[3:7])
    F_ij, F_ji = dense_flow(fi.rgb, fj.rgb)
    R, t = prior._pose(F_ij, F_ji, seq.K)[:2]
    # DIS flow on the procedural textures is good to ~0.15 px, which leaves ~1° of rotation and
    # ~10° of translation direction at these baselines (exact correspondences: test above).
    assert _rot_err_deg(R, R_gt) < 2.0
    assert _dir_err_deg(t, T[:3]) < 20.0
    # Depth of image i up to one scale, where the prior is confident.
    conf = p.C_ii > 5
    assert conf.mean() > 0.1
    s = np.median(fi.depth[conf] / p.X_ii[..., 2][conf])
    rel = np.abs(s * p.X_ii[..., 2][conf] - fi.depth[conf]) / fi.depth[conf]
    assert np.median(rel) < 0.15
    # X_ji: image j's points in camera i, with the same scale.
    X_jj = backproject(fj.depth, seq.K)
    X_ji_gt = sim3.act(sim3.inv(T), X_jj.reshape(-1, 3)).reshape(H, W, 3)
    cj = p.C_ji > 5
    err = np.linalg.norm(s * p.X_ji[cj] - X_ji_gt[cj], axis=-1) / np.linalg.norm(
        X_ji_gt[cj], axis=-1
    )
    assert np.median(err) < 0.15
    # Normalised: median distance of the confident-or-not triangulated points is ~1.
    assert 0.5 < np.median(np.linalg.norm(p.X_ii, axis=-1)) < 2.0


def test_confidence_is_higher_where_the_depth_is_right(seq):
    prior = TwoViewPrior(seq.K, (W, H))
    p = prior.pair(seq[0], seq[4])
    z = seq[0].depth
    s = np.median(z / p.X_ii[..., 2])
    rel = np.abs(s * p.X_ii[..., 2] - z) / z
    hi, lo = p.C_ii > 5, p.C_ii < 1.5
    assert np.median(rel[hi]) < np.median(rel[lo])


def _still(seq, i):
    """Frame i again under another index: zero baseline, zero rotation."""
    return dataclasses.replace(seq[i], index=10_000)


def _rotated(seq, i, deg):
    """Frame i after a pure rotation about the camera centre (no parallax), rendered."""
    from mslam_ref.synthetic import render

    rot = np.concatenate([np.zeros(3), so3.exp(np.radians([0.0, deg, 0.0])), [1.0]])
    T_WC = sim3.mul(seq[i].T_WC, rot)
    rgb, depth = render(seq.scene, T_WC, seq.K, W, H)[:2]
    return dataclasses.replace(seq[i], index=20_000, rgb=rgb, depth=depth, T_WC=T_WC)


@pytest.mark.parametrize("make", ["still", "rotation"])
def test_degenerate_pairs_are_flagged_not_invented(seq, make):
    prior = TwoViewPrior(seq.K, (W, H))
    fi = seq[0]
    if make == "still":
        fj = _still(seq, 0)
    else:
        fj = _rotated(seq, 0, 3.0)
    p = prior.pair(fi, fj)
    check_prediction(p)
    assert prior.last_status in ("parallax", "few_inliers")
    assert np.all(p.C_ii == 1.0) and np.all(p.C_ji == 1.0)
    assert np.all(p.Q_ji == FAILED_Q)
    # Fronto-parallel planes: no depth structure is claimed.
    assert np.ptp(p.X_ii[..., 2]) < 1e-12


def test_mono_is_a_plane_until_a_pair_gave_depth(seq):
    prior = TwoViewPrior()  # uncalibrated: focal guess
    X, C = prior.mono(seq[0])
    assert X.shape == (H, W, 3) and np.all(C == 1.0)
    assert np.ptp(X[..., 2]) < 1e-12
    prior.pair(seq[0], seq[4])
    assert prior.last_status == "ok"
    X0, C0 = prior.mono(seq[0])
    X2, _ = prior.mono(seq[4])
    assert np.ptp(X0[..., 2]) > 0.1 and C0.max() > 5
    # Image j's remembered pointmap is in its own camera: its depth matches the truth up to scale.
    z = seq[4].depth
    s = np.median(z / X2[..., 2])
    assert np.median(np.abs(s * X2[..., 2] - z) / z) < 0.15


def test_bad_input_is_one_line_errors(seq):
    with pytest.raises(ValueError, match="K"):
        TwoViewPrior(np.eye(2), (W, H))
    with pytest.raises(ValueError, match="fb_px"):
        TwoViewPriorConfig(fb_px=0)
    small = dataclasses.replace(seq[1], rgb=seq[1].rgb[:48, :64], depth=None)
    with pytest.raises(ValueError, match="frame_j"):
        TwoViewPrior().pair(seq[0], small)


def test_homography_parallax_grows_with_baseline(seq):
    par = []
    for j in (1, 4):
        F_ij, F_ji = dense_flow(seq[0].rgb, seq[j].rgb)
        e, _ = forward_backward_error(F_ij, F_ji)
        v, u = np.nonzero(e < 1.0)
        uv = np.stack([u, v], -1).astype(float)
        par.append(homography_parallax(uv, uv + F_ij[v, u], seq.K))
    assert 0.1 < par[0] < par[1]


def test_system_waits_for_parallax_then_poses_the_waiting_frames(seq):
    """The frontend fixes keyframe 0 only once a pair has parallax, then poses the frames it
    kept waiting; keyframe 0's pointmap is triangulated, not mono's plane."""
    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.system.frontend import SlamSystem

    system = SlamSystem(TwoViewPrior(), load_config("twoview"), load_kernels("ref"))
    statuses = [system.process(seq[i]) for i in range(8)]
    assert statuses[0] == "waiting"
    first = statuses.index("keyframe")
    kf0 = system.keyframes[0]
    assert kf0.frame.index == 0 and system.keyframes[1].frame.index == first
    z = kf0.state.X_canon[:, 2]
    assert np.ptp(z) > 0.1 * np.median(z)
    idx, _, T = system.frame_poses()
    # Waiting frames are tracked afterwards (against keyframe 1, or keyframe 0 when their pair
    # with keyframe 1 is degenerate); only those without parallax to either stay unposed.
    assert {0, first} <= set(idx.tolist()) and len(idx) >= 6
    # Poses up to one Sim(3): the camera moves forward, so relative positions are collinear-ish
    # with the true ones (direction error of the chord from frame 0 to the last posed frame).
    gt = np.stack([seq[i].T_WC[:3] for i in idx])
    est = T[:, :3]
    d_gt, d_est = gt[-1] - gt[0], est[-1] - est[0]
    R0 = so3.to_matrix(seq[0].T_WC[3:7])  # both in camera-0 axes for the comparison
    cos = (R0.T @ d_gt) @ d_est / np.linalg.norm(d_gt) / np.linalg.norm(d_est)
    assert cos > np.cos(np.radians(20))


def test_waiting_frames_are_listed_in_frame_order(seq):
    """A camera at rest for the first frames: they wait with frame 0 and are posed when the
    wait ends, after the frame that ended it; ``frame_poses`` (and so ``trajectory.txt``)
    still lists every frame in frame order, as TUM tools expect."""
    import dataclasses

    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.system.frontend import SlamSystem

    order = [0, 0, 0, 1, 2, 3, 4, 5]  # frames 1 and 2 repeat frame 0's image
    frames = [dataclasses.replace(seq[i], index=k, timestamp=k / 30) for k, i in enumerate(order)]
    system = SlamSystem(TwoViewPrior(), load_config("twoview"), load_kernels("ref"))
    statuses = [system.process(f) for f in frames]
    assert statuses[:3] == ["waiting"] * 3
    recorded = [p.index for p in system.poses if p.kf >= 0]
    assert recorded != sorted(recorded)  # the waiting frames were posed after a later one
    idx, ts, _ = system.frame_poses()
    assert {0, 1, 2} <= set(idx.tolist())
    assert np.all(np.diff(idx) > 0) and np.all(np.diff(ts) > 0)


def test_cli_runs_an_rgb_image_folder_with_the_twoview_prior(seq, tmp_path, capsys):
    """An image folder has no depth: without --prior it is a one-line error naming twoview;
    with --prior twoview it runs with the packaged twoview config (focal-length guess)."""
    import json

    import cv2

    from mslam.cli import main

    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(0, 12, 2):
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.cvtColor(seq[i].rgb, cv2.COLOR_RGB2BGR))
    out = tmp_path / "out"
    assert main(["run", str(folder), "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err.strip()
    assert "--prior twoview" in err and len(err.splitlines()) == 1
    args = ["run", str(folder), "--out", str(out), "--prior", "twoview", "--kernels", "ref"]
    assert main([*args, "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["prior"] == "twoview" and s["frames"] == 6 and not s["calibrated"]
    assert s["prior_metric"] is False
    assert s["config"]["tracking"]["match_frac_thresh"] == 0.45
    assert s["frames_with_pose"] >= 4


def test_cli_runs_a_video_with_the_twoview_prior(seq, tmp_path):
    """A video file (MJPG .avi: lossy frames) runs RGB-only end to end like an image folder."""
    import json

    import cv2

    from mslam.cli import main

    path = tmp_path / "clip.avi"
    H, W = seq[0].rgb.shape[:2]
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (W, H))
    if not wr.isOpened():
        pytest.skip("OpenCV build cannot write MJPG video")
    for i in range(0, 12, 2):
        wr.write(cv2.cvtColor(seq[i].rgb, cv2.COLOR_RGB2BGR))
    wr.release()
    out = tmp_path / "out"
    args = ["run", str(path), "--out", str(out), "--prior", "twoview", "--kernels", "ref"]
    assert main([*args, "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["prior"] == "twoview" and s["frames"] == 6
    assert s["frames_with_pose"] >= 4
