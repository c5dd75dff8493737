"""Priors: protocol invariants, the synthetic noise model, descriptors, MASt3R activations."""

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
