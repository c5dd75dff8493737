"""Priors: protocol invariants, the synthetic noise model, the RGB-D prior, MASt3R activations."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from stand_ins import StandInMast3r
from tolerances import F32_UNIT, F64_IDENTITY, F64_ULPS, NOISE_STD, SERIES_NEAR_ZERO

from mslam.datasets.synthetic import make_sequence
from mslam.priors import DESC_DIM, PairPrediction, Prior, check_prediction
from mslam.priors.descriptors import descriptor_Q, patch_descriptors
from mslam.priors.synthetic import SyntheticPrior, SyntheticPriorConfig
from mslam_ref import sim3
from mslam_ref.pointmap import backproject

W, H = 64, 48


@pytest.fixture(scope="module")
def seq():
    return make_sequence("loop", n_frames=30, width=W, height=H, seed=0)


def test_synthetic_prior_protocol(seq) -> None:
    prior = SyntheticPrior(seq)
    assert isinstance(prior, Prior)
    pred = prior.pair(seq[0], seq[2])
    check_prediction(pred)
    assert pred.X_ii.shape == (H, W, 3) and pred.D_ji.shape == (H, W, DESC_DIM)
    X, C = prior.mono(seq[1])
    assert X.shape == (H, W, 3) and C.shape == (H, W) and C.min() >= 1.0
    # Deterministic by seed and frame indices; a different seed changes the noise.
    again = prior.pair(seq[0], seq[2])
    np.testing.assert_array_equal(pred.X_ji, again.X_ji)
    np.testing.assert_array_equal(pred.D_ii, again.D_ii)
    other = SyntheticPrior(seq, SyntheticPriorConfig(seed=1)).pair(seq[0], seq[2])
    assert not np.array_equal(pred.X_ji, other.X_ji)


def test_noise_free_prior_is_ground_truth(seq) -> None:
    cfg = SyntheticPriorConfig(
        depth_sigma0=0, depth_sigma2=0, outlier_frac=0, pair_log_scale_sigma=0,
        rel_trans_sigma=0, rel_rot_sigma=0, rel_log_scale_sigma=0,
    )  # fmt: skip
    fi, fj = seq[3], seq[5]
    pred = SyntheticPrior(seq, cfg).pair(fi, fj)
    np.testing.assert_allclose(pred.X_ii, backproject(fi.depth, seq.K), atol=F64_IDENTITY)
    T_ij = sim3.mul(sim3.inv(fi.T_WC), fj.T_WC)
    np.testing.assert_allclose(
        pred.X_ji, sim3.act(T_ij, backproject(fj.depth, seq.K)), atol=F64_IDENTITY
    )


def test_depth_noise_statistics(seq) -> None:
    cfg = SyntheticPriorConfig(
        depth_sigma0=0.01, depth_sigma2=0.005, noise_blur_px=1.0, outlier_frac=0.0,
        pair_log_scale_sigma=0.0,
    )  # fmt: skip
    prior = SyntheticPrior(seq, cfg)
    r = []
    for i in range(0, 30, 3):
        f = seq[i]
        X, _ = prior.mono(f)
        r.append(((X[..., 2] - f.depth) / prior.sigma(f.depth)).ravel())
    r = np.concatenate(r)
    assert abs(r.mean()) < 0.1
    assert 0.85 < r.std() < 1.15


def test_outliers_and_confidence(seq) -> None:
    cfg = SyntheticPriorConfig(outlier_frac=0.2, pair_log_scale_sigma=0.0, depth_sigma2=0.0)
    prior = SyntheticPrior(seq, cfg)
    f = seq[4]
    X, C = prior.mono(f)
    rel = np.abs(np.log(X[..., 2] / f.depth))
    out = rel > 0.15  # outliers move depth by >= exp(0.2); inlier noise is ~2 mm
    assert 0.15 < out.mean() < 0.25
    assert np.all(C[out] <= 1.5) and np.median(C[~out]) > 10
    # Confidence falls with the noise level, i.e. with depth.
    c = SyntheticPrior(seq, SyntheticPriorConfig(outlier_frac=0.0))
    _, C2 = c.mono(f)
    near, far = f.depth < np.quantile(f.depth, 0.2), f.depth > np.quantile(f.depth, 0.8)
    assert np.median(C2[near]) > np.median(C2[far])


def test_pair_scale_and_sim3_error_statistics(seq) -> None:
    cfg = SyntheticPriorConfig(
        pair_log_scale_sigma=0.05, rel_trans_sigma=0.02, rel_rot_sigma=0.01,
        rel_log_scale_sigma=0.03,
    )  # fmt: skip
    prior = SyntheticPrior(seq, cfg)
    xis, scales = [], []
    for i in range(30):
        for j in range(i + 1, min(i + 8, 30)):
            s, E = prior.pair_errors(seq[i], seq[j])
            scales.append(np.log(s))
            xis.append(sim3.log(E))
    xis, scales = np.array(xis), np.array(scales)
    assert len(scales) > 150
    assert 0.04 < scales.std() < 0.06
    np.testing.assert_allclose(xis.std(axis=0), [0.02] * 3 + [0.01] * 3 + [0.03], rtol=NOISE_STD)
    # The errors are what pair() applies (no other noise): X_ji = s E T_ij X_jj.
    clean = replace(cfg, depth_sigma0=0.0, depth_sigma2=0.0, outlier_frac=0.0)
    p2 = SyntheticPrior(seq, clean)
    fi, fj = seq[2], seq[6]
    s, E = p2.pair_errors(fi, fj)
    pred = p2.pair(fi, fj)
    T = sim3.mul(E, sim3.mul(sim3.inv(fi.T_WC), fj.T_WC))
    np.testing.assert_allclose(
        pred.X_ji, s * sim3.act(T, backproject(fj.depth, seq.K)), atol=F64_IDENTITY
    )
    np.testing.assert_allclose(pred.X_ii, s * backproject(fi.depth, seq.K), atol=F64_IDENTITY)


def test_covisibility_lowers_confidence(seq) -> None:
    prior = SyntheticPrior(seq, SyntheticPriorConfig(outlier_frac=0.0))
    fi, fj = seq[0], seq[4]
    pred = prior.pair(fi, fj)
    cov = prior.covisible(fi, fj)
    assert 0.2 < cov.mean() < 1.0
    assert np.median(pred.C_ji[cov]) > 2 * np.median(pred.C_ji[~cov])
    assert np.median(pred.Q_ji[cov]) > 1.5 > np.median(pred.Q_ji[~cov])


def test_patch_descriptors_discriminate(seq) -> None:
    D, contrast = patch_descriptors(seq[0].rgb)
    assert D.shape == (H, W, DESC_DIM) and contrast.shape == (H, W)
    np.testing.assert_allclose(np.linalg.norm(D, axis=-1), 1.0, atol=F32_UNIT)  # float32
    # A pixel is more similar to itself shifted by one pixel than to random pixels.
    near = (D[:, 1:] * D[:, :-1]).sum(-1).mean()
    rng = np.random.default_rng(0)
    far = (D.reshape(-1, DESC_DIM) * rng.permutation(D.reshape(-1, DESC_DIM))).sum(-1).mean()
    assert near > far + 0.3
    flat = patch_descriptors(np.full((8, 8, 3), 120, np.uint8))[0]
    np.testing.assert_allclose(np.linalg.norm(flat, axis=-1), 1.0, atol=F32_UNIT)  # float32


def test_descriptor_Q_is_every_priors_Q(seq) -> None:
    """One formula for Q: the synthetic, RGB-D and two-view priors return exactly
    ``descriptor_Q`` of the patch contrast (bit for bit) where they do not lower it."""
    from mslam.priors.rgbd import RGBDPrior
    from mslam.priors.twoview import TwoViewPrior

    _, contrast = patch_descriptors(seq[3].rgb)
    Q = descriptor_Q(contrast, 6.0, 0.04)
    np.testing.assert_array_equal(Q, 1.0 + 6.0 * np.tanh(contrast / 0.04))
    assert Q.min() >= 1.0 and Q.max() <= 7.0
    order = np.argsort(contrast, axis=None)
    assert np.all(np.diff(Q.reshape(-1)[order]) >= 0)  # monotone in the contrast
    np.testing.assert_array_equal(RGBDPrior(seq)._desc(seq[3])[1], Q)
    np.testing.assert_array_equal(TwoViewPrior()._desc(seq[3])[1], Q)
    clean = SyntheticPrior(seq, SyntheticPriorConfig(outlier_frac=0.0))
    np.testing.assert_array_equal(clean.pair(seq[3], seq[4]).Q_ii, Q)


def test_check_prediction_rejects_bad_outputs(seq) -> None:
    pred = SyntheticPrior(seq).pair(seq[0], seq[1])
    with pytest.raises(ValueError, match="C_ii"):
        check_prediction(replace(pred, C_ii=pred.C_ii - 1.0))
    with pytest.raises(ValueError, match="Q_ji"):
        check_prediction(replace(pred, Q_ji=-pred.Q_ji))
    with pytest.raises(ValueError, match="D_ii"):
        check_prediction(replace(pred, D_ii=2 * pred.D_ii))
    with pytest.raises(ValueError, match="X_ji"):
        PairPrediction(*(getattr(pred, k) for k in ("X_ii", "C_ii", "D_ii", "Q_ii")),
                       pred.X_ji[..., :2], pred.C_ji, pred.D_ji, pred.Q_ji)  # fmt: skip
    with pytest.raises(ValueError, match="depth"):
        from mslam.datasets import Frame

        SyntheticPrior(seq).mono(Frame(0, 0.0, seq[0].rgb))


# -- RGB-D prior ----------------------------------------------------------------------------

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
    assert prior.cfg.desc.kind == "dense"
    cfg = load_config("rgbd", ["rgbd_prior.descriptors=separable"])
    assert cfg.rgbd_prior().desc.kind == "separable"
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


def test_mast3r_activations() -> None:
    from mslam.priors.mast3r import (
        conf_activation,
        desc_activation,
        desc_conf_activation,
        pts3d_activation,
    )

    v = np.array([[3.0, 0.0, 4.0], [0.0, 0.0, 0.0], [1e-8, 0, 0]])
    out = pts3d_activation(v)
    np.testing.assert_allclose(out[0], np.array([0.6, 0, 0.8]) * np.expm1(5.0), rtol=F64_ULPS)
    np.testing.assert_array_equal(out[1], 0.0)
    np.testing.assert_allclose(out[2], v[2], rtol=SERIES_NEAR_ZERO)  # ~identity near 0
    assert np.all(conf_activation(np.array([-50.0, 0.0, 3.0])) >= 1.0)
    assert conf_activation(0.0) == 2.0
    assert np.all(desc_conf_activation(np.array([-30.0, 0.0])) > 0)
    d = desc_activation(np.random.default_rng(0).normal(size=(4, 5, 24)))
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=F64_ULPS)


def test_mast3r_adapter_with_stand_in() -> None:
    from mslam.priors.mast3r import Mast3rConfig, Mast3rPrior, NumpyBackend

    seq = make_sequence("loop", n_frames=4, width=W, height=H, seed=0)
    net = StandInMast3r()
    prior = Mast3rPrior(net, Mast3rConfig(apply_activations=True), backend=NumpyBackend())
    pred = prior.pair(seq[0], seq[1])
    check_prediction(pred)
    assert pred.X_ii.shape == (384, 512, 3) and pred.D_ji.shape == (384, 512, 24)
    assert np.median(pred.X_ii[..., 2]) < np.median(pred.X_ji[..., 2])  # head 1 vs head 2
    X, C = prior.mono(seq[0])
    assert X.shape == (384, 512, 3) and C.min() >= 1.0
    assert net.calls.count("encode") == 2  # encoder outputs are cached per frame
    assert prior.network_frame(seq[0]).rgb.shape == (384, 512, 3)
    K = prior.network_intrinsics(seq.K, seq[0])
    np.testing.assert_allclose(K[0, 0], seq.K[0, 0] * 8)
    with pytest.raises(ValueError, match="missing method _encode_image"):
        Mast3rPrior(object(), backend=NumpyBackend())


def test_mast3r_missing_dependencies(tmp_path, monkeypatch) -> None:
    from mslam.priors.mast3r import CHECKPOINT_ENV, load_mast3r, load_prior

    with pytest.raises(FileNotFoundError, match=r"missing\.pth"):
        load_mast3r(tmp_path / "missing.pth")
    monkeypatch.delenv(CHECKPOINT_ENV, raising=False)
    with pytest.raises(FileNotFoundError, match=CHECKPOINT_ENV):
        load_prior()
    ckpt = tmp_path / "w.pth"
    ckpt.write_bytes(b"x")
    try:
        import torch  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="torch is not installed"):
            load_mast3r(ckpt)
        with pytest.raises(ValueError, match="torch is not installed"):
            load_prior(ckpt)
    else:
        pytest.importorskip("mast3r")


def test_mast3r_torch_backend() -> None:
    torch = pytest.importorskip("torch")
    from mslam.priors.mast3r import TorchBackend

    b = TorchBackend("cpu")
    t = b.to_tensor(np.ones((2, 3), np.float32))
    assert isinstance(t, torch.Tensor)
    np.testing.assert_array_equal(b.to_numpy(b.as_float(t)), np.ones((2, 3)))


def test_mast3r_adapter_with_stand_in_torch_module() -> None:
    """The adapter drives a torch ``nn.Module`` with upstream's interface (encoder on 16x16
    patches, two-view decoder, per-view heads returning raw outputs) through ``TorchBackend``."""
    torch = pytest.importorskip("torch")
    from mslam.priors.mast3r import Mast3rConfig, Mast3rPrior, TorchBackend

    class StandIn(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            torch.manual_seed(0)
            self.embed = torch.nn.Conv2d(3, 16, kernel_size=16, stride=16)
            self.mix = torch.nn.Linear(32, 16)
            self.heads = torch.nn.ModuleList([torch.nn.Linear(16, 256 * 29) for _ in range(2)])
            self.encoded = 0

        def _encode_image(self, img, true_shape):
            self.encoded += 1
            feat = self.embed(img).flatten(2).transpose(1, 2)  # (1, HW/256, 16)
            return feat, torch.zeros((*feat.shape[:2], 2), dtype=torch.long), None

        def _decoder(self, f1, p1, f2, p2):
            return [self.mix(torch.cat([f1, f2], -1))], [self.mix(torch.cat([f2, f1], -1))]

        def _downstream_head(self, head, toks, shape):
            H, W = (int(x) for x in shape[0])
            out = self.heads[head - 1](toks[-1]).reshape(1, H // 16, W // 16, 16, 16, 29)
            out = out.permute(0, 1, 3, 2, 4, 5).reshape(1, H, W, 29)
            return {
                "pts3d": out[..., :3] * 0.1 + torch.tensor([0.0, 0.0, 1.0]),
                "conf": out[..., 3],
                "desc": out[..., 4:28],
                "desc_conf": out[..., 28],
            }

    seq = make_sequence("loop", n_frames=3, width=W, height=H, seed=0)
    net = StandIn().eval()
    prior = Mast3rPrior(net, Mast3rConfig(apply_activations=True), backend=TorchBackend("cpu"))
    pred = prior.pair(seq[0], seq[1])
    check_prediction(pred)  # C >= 1, unit descriptors, Q > 0, finite
    assert pred.X_ii.shape == (384, 512, 3) and pred.D_ji.shape == (384, 512, 24)
    assert pred.X_ii.dtype == np.float64
    again = prior.pair(seq[0], seq[1])
    np.testing.assert_array_equal(again.X_ji, pred.X_ji)  # deterministic
    assert net.encoded == 2  # encoder outputs cached per frame
    feats = [t for enc in (prior._encode(seq[0]), prior._encode(seq[1])) for t in enc]
    assert prior.cache.bytes == sum(t.nbytes for t in feats) > 0  # tensors count their bytes
    X, C = prior.mono(seq[2])
    assert X.shape == (384, 512, 3) and np.all(C >= 1.0)
