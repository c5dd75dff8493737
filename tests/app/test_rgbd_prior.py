"""The RGB-D prior: depth filling, ICP, keypoints on a downscaled copy, its config, relative
poses on synthetic frames and on the 7-Scenes clip, degenerate pairs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mslam.datasets.synthetic import make_sequence
from mslam.priors import check_prediction
from mslam_ref import sim3
from mslam_ref.pointmap import backproject

W, H = 64, 48


SEVEN_PAIRS = [(0, 5), (20, 30), (50, 60), (100, 110), (130, 140)]


def _pose_error(T_est, T_gt) -> tuple[float, float]:
    from mslam_ref import so3

    E = sim3.mul(sim3.inv(T_gt), T_est)
    return float(np.degrees(np.linalg.norm(so3.log(E[3:7])))), float(
        np.linalg.norm(T_est[:3] - T_gt[:3])
    )


def test_fill_depth() -> None:
    from mslam.priors.rgbd import fill_depth

    z = np.array([[0.0, 2.0, 0.0], [0.0, 0.0, 3.0]])
    f, valid = fill_depth(z)
    assert valid.sum() == 2 and np.all(f > 0)
    assert f[0, 0] == 2.0 and f[1, 2] == 3.0 and f[0, 2] in (2.0, 3.0)
    f0, v0 = fill_depth(np.zeros((2, 2)), default=4.0)
    assert np.all(f0 == 4.0) and not v0.any()


def test_icp_target_normals_and_cache() -> None:
    """ICP's normals (a hand-written cross product, only at the pixels asked for) are the unit
    ``du × dv`` of central differences, marked invalid at holes and borders; the prior keeps
    each frame's target (its points and their validity) once."""
    from mslam.priors.rgbd import RGBDPrior
    from mslam.priors.rgbd_pose import icp_target, normals_at

    rng = np.random.default_rng(3)
    z = 1.0 + rng.random((30, 40))
    z[5:9, 10:20] = 0.0
    K = np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    Y, has_normal = icp_target(z, K)
    X = backproject(z, K)
    assert np.array_equal(Y, X.reshape(-1, 3).T)
    N, ok = normals_at(Y, has_normal, 40, np.arange(30 * 40))
    ok2 = ok.reshape(30, 40)
    n = np.cross(X[1:-1, 2:] - X[1:-1, :-2], X[2:, 1:-1] - X[:-2, 1:-1])
    n = n[ok2[1:-1, 1:-1]] / np.linalg.norm(n[ok2[1:-1, 1:-1]], axis=-1, keepdims=True)
    assert not ok2[0].any() and not ok2[-1].any() and not ok2[:, 0].any() and not ok2[:, -1].any()
    # The 4 x 10 hole and its 4-neighbours are marked (no diagonals): 40 + 8 + 20 pixels.
    assert not ok2[5:9, 9:21].any() and not ok2[4:10, 10:20].any() and ok2[4, 9]
    assert ok2.sum() == 28 * 38 - 68
    assert np.allclose(N.T.reshape(30, 40, 3)[1:-1, 1:-1][ok2[1:-1, 1:-1]], n)
    assert not N[:, ~ok].any()
    # Any subset of pixels, in any order, gets the same normals.
    some = rng.permutation(30 * 40)[:100]
    N_some, ok_some = normals_at(Y, has_normal, 40, some)
    assert np.array_equal(N_some, N[:, some]) and np.array_equal(ok_some, ok[some])
    seq = make_sequence("forward", n_frames=20, width=160, height=120, seed=0)
    prior = RGBDPrior(seq)
    assert prior.relative_pose(seq[10], seq[13])[1] >= 15
    assert prior._icp_target(seq[10]) is prior._icp_target(seq[10])


def test_rgbd_prior_detects_on_a_downscaled_copy() -> None:
    """``detect_max_width``: keypoints found on a smaller copy come back in frame pixels, so
    the pose is as right as with full-size detection (fewer keypoints, fewer inliers)."""
    from mslam.priors.rgbd import RGBDPrior, RGBDPriorConfig

    seq = make_sequence("forward", n_frames=20, width=320, height=240, seed=0)
    full = RGBDPrior(seq, replace(RGBDPriorConfig(), detect_min_width=0))
    small = RGBDPrior(seq, replace(RGBDPriorConfig(), detect_min_width=0, detect_max_width=160))
    uv_full = full._detect(seq[10])[0]
    uv_small = small._detect(seq[10])[0]
    assert uv_small[:, 0].max() > 200 and uv_small[:, 1].max() > 150  # frame pixels
    assert len(uv_small) < len(uv_full)
    truth = sim3.mul(sim3.inv(seq[10].T_WC), seq[13].T_WC)
    for prior in (full, small):
        T, n = prior.relative_pose(seq[10], seq[13])
        rot, trans = _pose_error(T, truth)
        assert n >= 15 and rot < 1.0 and trans < 0.03


def test_rgbd_prior_config_comes_from_the_run_config() -> None:
    """``rgbd_prior.*`` in base.yaml are the dataclass defaults, and --set reaches the prior."""
    from mslam.config import load_config
    from mslam.priors.rgbd import RGBDPriorConfig
    from mslam.system.sources import _make_prior

    assert load_config().rgbd_prior() == RGBDPriorConfig()
    cfg = load_config("rgbd", ["rgbd_prior.icp_points=3000", "rgbd_prior.features=orb"])
    seq = make_sequence("forward", n_frames=3, width=80, height=60, seed=0)
    prior = _make_prior("rgbd", seq, False, cfg)
    assert prior.cfg.icp_points == 3000 and prior.cfg.features == "orb"
    assert prior.cfg.n_features == RGBDPriorConfig().n_features
    assert prior.cfg.desc.kind == "separable"
    cfg = load_config("rgbd", ["rgbd_prior.descriptors=dense"])
    assert cfg.rgbd_prior().desc.kind == "dense"
    # Checked when the config is loaded, whichever prior the run uses.
    with pytest.raises(ValueError, match=r"rgbd_prior\.descriptors: expected 'dense' or"):
        load_config(None, ["rgbd_prior.descriptors=sparse"])
    with pytest.raises(ValueError, match=r"rgbd_prior\.features: expected 'sift' or"):
        load_config(None, ["rgbd_prior.features=surf"])


def test_rgbd_prior_on_synthetic_frames() -> None:
    from mslam.priors.rgbd import RGBDPrior

    seq = make_sequence("forward", n_frames=40, width=160, height=120, seed=0)
    prior = RGBDPrior(seq)
    fi, fj = seq[10], seq[13]
    d = fj.depth.copy()
    d[:10] = 0.0  # invalid depth rows are filled with confidence 1
    fj = type(fj)(fj.index, fj.timestamp, fj.rgb, d, fj.T_WC)
    T, n = prior.relative_pose(fi, fj)
    rot, trans = _pose_error(T, sim3.mul(sim3.inv(fi.T_WC), fj.T_WC))
    assert n >= 15 and rot < 1.0 and trans < 0.03
    pred = prior.pair(fi, fj)
    check_prediction(pred)
    # Every sub-step of the pair was timed (the profiles' prior table), and nothing else.
    steps = {"features", "ratio", "pnp", "icp", "depth", "descriptors", "consistency"}
    assert set(prior.seconds) == steps and all(v > 0 for v in prior.seconds.values())
    X, C = prior.mono(fj)
    assert np.all(C[:10] == 1.0) and np.all(C[10:] > 2.0) and np.all(X[..., 2] > 0)
    # Frames at another resolution: K is rescaled, the pose stays right.
    small = make_sequence("forward", n_frames=40, width=80, height=60, seed=0)
    T2, _ = prior.relative_pose(small[10], small[13])
    assert _pose_error(T2, sim3.mul(sim3.inv(fi.T_WC), seq[13].T_WC))[1] < 0.05


def test_rgbd_prior_relative_pose_7scenes(shared_data) -> None:
    """Relative-pose error of features + depth + PnP on real frames (working size 160x120)."""
    from mslam.datasets import load_sequence
    from mslam.priors.rgbd import RGBDPrior

    seq = load_sequence(shared_data / "seq" / "7scenes_redkitchen_f000000-000149", size=(160, 120))
    prior = RGBDPrior(seq)
    errs = []
    for i, j in SEVEN_PAIRS:
        fi, fj = seq[i], seq[j]
        T, n = prior.relative_pose(fi, fj)
        rot, trans = _pose_error(T, sim3.mul(sim3.inv(fi.T_WC), fj.T_WC))
        print(
            f"7-Scenes pair ({i},{j}): {n} inliers, rot {rot:.2f} deg, trans {100 * trans:.2f} cm"
        )
        errs.append((rot, trans))
    errs = np.array(errs)
    assert np.all(errs[:, 0] < 2.0) and np.all(errs[:, 1] < 0.05)
    pred = prior.pair(seq[20], seq[30])
    check_prediction(pred)
    assert (pred.C_ji > 2).mean() > 0.5


def test_rgbd_prior_rejects_degenerate_pnp(monkeypatch) -> None:
    """EPnP-in-RANSAC can return a pose 1e13 m away with "inliers"; it must not escape."""
    import cv2

    from mslam.priors import rgbd
    from mslam.priors.rgbd import FAILED_Q, RGBDPrior

    seq = make_sequence("forward", n_frames=40, width=160, height=120, seed=0)
    prior = RGBDPrior(seq)
    fi, fj = seq[10], seq[13]
    T_gt = sim3.mul(sim3.inv(fi.T_WC), fj.T_WC)
    real = cv2.solvePnPRansac
    calls = []

    def bad_epnp(obj, img, K, dist, **kw):
        calls.append(kw["flags"])
        found, rvec, tvec, inl = real(obj, img, K, dist, **kw)
        if kw["flags"] == cv2.SOLVEPNP_EPNP:
            return True, rvec, np.array([[1e13], [-3e12], [5e12]]), inl
        return found, rvec, tvec, inl

    monkeypatch.setattr(rgbd.cv2, "solvePnPRansac", bad_epnp)
    T, n = prior.relative_pose(fi, fj)
    assert calls == [cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE]  # guarded, then the fallback
    assert n >= 15 and _pose_error(T, T_gt)[1] < 0.03

    def always_bad(obj, img, K, dist, **kw):
        _found, rvec, tvec, inl = real(obj, img, K, dist, **kw)
        return True, rvec, -np.abs(tvec) - 50.0, inl  # far away and behind the camera

    monkeypatch.setattr(rgbd.cv2, "solvePnPRansac", always_bad)
    T, n = prior.relative_pose(fi, fj)
    assert n == 0 and np.array_equal(T, sim3.identity())
    pred = prior.pair(fi, fj)  # a failed pose gives no trusted correspondence
    check_prediction(pred)
    assert np.all(pred.C_ji == 1.0) and np.all(pred.Q_ji == FAILED_Q)
    assert np.all(np.sqrt(pred.Q_ii.max() * pred.Q_ji) < 1.5)  # below upstream's Q_conf


def test_rgbd_prior_7scenes_degenerate_pairs(shared_data) -> None:
    """Pairs where unguarded EPnP returned ~1e13 m: a sane pose or an honest failure."""
    from mslam.datasets import load_sequence
    from mslam.priors.rgbd import RGBDPrior

    seq = load_sequence(shared_data / "seq" / "7scenes_redkitchen_f000000-000149", size=(160, 120))
    prior = RGBDPrior(seq)
    for i, j in [(98, 77), (99, 77), (98, 61)]:
        T, n = prior.relative_pose(seq[i], seq[j])
        assert np.all(np.isfinite(T))
        if n >= prior.cfg.min_inliers:
            rot, trans = _pose_error(T, sim3.mul(sim3.inv(seq[i].T_WC), seq[j].T_WC))
            assert rot < 3.0 and trans < 0.06, (i, j, rot, trans)
        else:
            assert np.array_equal(T, sim3.identity())


# -- MASt3R adapter -------------------------------------------------------------------------
