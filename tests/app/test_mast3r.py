"""MASt3R adapter without torch: upstream's network input, load-time errors, keyframe features,
settings from the config.

torch and the mast3r code are replaced by fakes: ``FakeTorch.load`` unpickles a file, and a
``mast3r`` package written into a temporary folder plays the user's checkout.
"""

from __future__ import annotations

import argparse
import pickle
import re
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image
from stand_ins import StandInMast3r

from mslam.cli import main
from mslam.datasets.frame import Frame
from mslam.priors import mast3r, mast3r_load
from mslam.priors.mast3r import Mast3rConfig, Mast3rPrior, NumpyBackend

ROOT = Path(__file__).resolve().parents[2]


def _frame(index: int, W: int, H: int) -> Frame:
    rng = np.random.default_rng(index)
    rgb = rng.integers(0, 256, (H // 4, W // 4, 3), dtype=np.uint8).repeat(4, 0).repeat(4, 1)
    return Frame(index, float(index), np.ascontiguousarray(rgb[:H, :W]), None, None)


def _prior(size: int = 224, **kw) -> tuple[Mast3rPrior, StandInMast3r]:
    net = StandInMast3r()
    cfg = Mast3rConfig(size=size, apply_activations=True, **kw)
    return Mast3rPrior(net, cfg, backend=NumpyBackend()), net


# -- network input --------------------------------------------------------------------------


def _upstream_input(rgb: np.ndarray, size: int) -> np.ndarray:
    """Upstream's rule written out with Pillow: resize (LANCZOS shrinking the long side, else
    BICUBIC), centre crop, ``(x / 255 - 0.5) / 0.5`` in float32, NCHW."""
    H1, W1 = rgb.shape[:2]
    long_edge = size if size == 512 else round(size * max(W1 / H1, H1 / W1))
    S = max(W1, H1)
    W, H = round(W1 * long_edge / S), round(H1 * long_edge / S)
    filt = Image.Resampling.LANCZOS if S > long_edge else Image.Resampling.BICUBIC
    img = Image.fromarray(rgb).resize((W, H), filt)
    cx, cy = W // 2, H // 2
    if size == 224:
        hw = hh = min(cx, cy)
    else:
        hw, hh = ((2 * cx) // 16) * 8, ((2 * cy) // 16) * 8
    x = np.asarray(img.crop((cx - hw, cy - hh, cx + hw, cy + hh))).astype(np.float32) / 255
    return ((x - np.float32(0.5)) / np.float32(0.5)).transpose(2, 0, 1)[None]


@pytest.mark.parametrize(
    "W, H, size", [(64, 48, 512), (640, 480, 512), (640, 480, 224), (48, 80, 224)]
)
def test_network_input_is_pillows_resize_bit_for_bit(W, H, size):
    prior, net = _prior(size)
    frame = _frame(3, W, H)
    prior.mono(frame)
    expected = _upstream_input(frame.rgb, size)
    assert net.inputs[0].dtype == np.float32 and net.inputs[0].shape == expected.shape
    np.testing.assert_array_equal(net.inputs[0], expected)
    np.testing.assert_array_equal(
        prior.network_frame(frame).rgb, np.round((expected[0] * 0.5 + 0.5) * 255).transpose(1, 2, 0)
    )


# -- loading: one-line errors at load time, nothing on stdout -------------------------------


class FakeTorch:
    """``torch.load`` as pickle; memory mapping is refused, as for an old-format file."""

    @staticmethod
    def load(path, map_location=None, weights_only=True, mmap=False):
        assert map_location == "cpu" and weights_only is False
        if mmap:
            raise RuntimeError("mmap can only be used with files saved with zipfile")
        with open(path, "rb") as f:
            return pickle.load(f)


_GOOD_MODEL = """
from stand_ins import StandInMast3r

print("Warning, a note the mast3r code prints at import")


class AsymmetricMASt3R(StandInMast3r):
    @classmethod
    def from_pretrained(cls, path):
        print("instantiating : AsymmetricMASt3R(...)")
        print("<All keys matched successfully>")
        net = cls()
        net.path = path
        return net

    def to(self, device):
        self.device = device
        return self

    def eval(self):
        return self
"""


@pytest.fixture
def fake_install(tmp_path, monkeypatch):
    """``write(model_source)``: a fake torch and a ``mast3r`` package with that model.py."""
    for mod in (mast3r, mast3r_load):
        monkeypatch.setattr(mod, "import_torch", lambda: FakeTorch)
    for name in [m for m in sys.modules if m == "mast3r" or m.startswith("mast3r.")]:
        monkeypatch.delitem(sys.modules, name)
    root = tmp_path / "checkout"
    (root / "mast3r").mkdir(parents=True)
    (root / "mast3r" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(root))

    def write(source: str = _GOOD_MODEL) -> None:
        (root / "mast3r" / "model.py").write_text(source)
        sys.modules.pop("mast3r.model", None)

    write()
    return write


def _checkpoint(tmp_path, content, name="w.pth") -> Path:
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else pickle.dumps(content))
    return path


_MASt3R = {
    "args": argparse.Namespace(model="AsymmetricMASt3R(output_mode='pts3d+desc24')"),
    "model": {
        "downstream_head1.dpt.head.0.weight": np.zeros(2),
        "downstream_head1.head_local_features.fc1.weight": np.zeros(2),
    },
}
_DUSt3R = {
    "args": argparse.Namespace(model="AsymmetricCroCo3DStereo(output_mode='pts3d')"),
    "model": {"downstream_head1.dpt.head.0.weight": np.zeros(2)},
}


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_loader_prints_nothing_on_stdout(tmp_path, fake_install, capsys):
    ckpt = _checkpoint(tmp_path, _MASt3R)
    prior = mast3r.load_prior(ckpt, Mast3rConfig(device="cpu", size=224))
    assert isinstance(prior, Mast3rPrior) and prior.model.path == str(ckpt)
    assert prior.model.device == "cpu" and prior.cfg.size == 224
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize(
    "content, expected",
    [
        (b"\x00 not a checkpoint", "not a readable PyTorch checkpoint"),
        ({"model": _MASt3R["model"]}, "has no 'args'"),
        ({"args": argparse.Namespace(), "model": {}}, "no 'model' description"),
        ({"args": _MASt3R["args"]}, "no 'model' weights"),
        (_DUSt3R, "no descriptor heads"),
    ],
    ids=["corrupt", "no-args", "args-without-model", "no-weights", "dust3r"],
)
def test_bad_checkpoints_fail_at_load_in_one_line(tmp_path, fake_install, content, expected):
    ckpt = _checkpoint(tmp_path, content)
    with pytest.raises(ValueError) as exc:
        mast3r.load_prior(ckpt)
    assert expected in _one_line(exc) and str(ckpt) in str(exc.value)
    assert not isinstance(exc.value, mast3r_load.Mast3rUnavailable)


def test_real_torch_checkpoints_are_read_and_checked(tmp_path):
    torch = pytest.importorskip("torch")
    weights = {k: torch.zeros(2) for k in _MASt3R["model"]}
    good = tmp_path / "mast3r.pth"
    torch.save({"args": _MASt3R["args"], "model": weights}, good)
    ckpt = mast3r_load.read_checkpoint(good, torch)  # memory-mapped
    mast3r_load.check_checkpoint(ckpt, good)
    dust3r = tmp_path / "dust3r.pth"
    torch.save(
        {"args": _DUSt3R["args"], "model": {"downstream_head1.dpt.w": torch.zeros(2)}}, dust3r
    )
    with pytest.raises(ValueError, match="no descriptor heads"):
        mast3r_load.check_checkpoint(mast3r_load.read_checkpoint(dust3r, torch), dust3r)
    broken = tmp_path / "broken.pth"
    broken.write_bytes(good.read_bytes()[:200])  # a truncated download
    with pytest.raises(ValueError) as exc:
        mast3r_load.read_checkpoint(broken, torch)
    assert "not a readable PyTorch checkpoint" in _one_line(exc)


def test_network_that_cannot_be_built_fails_in_one_line(tmp_path, fake_install):
    fake_install(
        _GOOD_MODEL.replace(
            'print("<All', 'raise RuntimeError("size\\nmismatch")\n        print("<All'
        )
    )
    with pytest.raises(ValueError) as exc:
        mast3r.load_prior(_checkpoint(tmp_path, _MASt3R))
    assert "cannot build the network" in _one_line(exc) and "size mismatch" in str(exc.value)


@pytest.mark.parametrize(
    "source, expected",
    [
        (
            "import einops\n",
            "mast3r cannot be imported: the Python module 'einops' is not installed (pip",
        ),
        ("import huggingface_hub.utils\n", "'huggingface_hub"),
        (None, "the Python module 'mast3r"),  # 'mast3r' or 'mast3r.model
        (
            'raise ImportError("dust3r is not initialized, could not find: /x/dust3r.\\n "'
            " \"Did you forget to run 'git submodule update --init --recursive' ?\")\n",
            "mast3r cannot be imported: dust3r is not initialized, could not find: /x/dust3r.",
        ),
    ],
    ids=["einops", "huggingface_hub", "mast3r", "dust3r-submodule"],
)
def test_missing_dependency_is_named(tmp_path, fake_install, monkeypatch, source, expected):
    monkeypatch.setitem(sys.modules, "einops", None)  # absent, whatever is installed
    monkeypatch.setitem(sys.modules, "huggingface_hub", None)
    if source is None:
        monkeypatch.setitem(sys.modules, "mast3r", None)
    else:
        fake_install(source)
    with pytest.raises(mast3r_load.Mast3rUnavailable) as exc:
        mast3r.load_prior(_checkpoint(tmp_path, _MASt3R))
    assert expected in _one_line(exc)


def test_cli_refuses_a_dust3r_checkpoint_before_the_first_frame(tmp_path, fake_install, capsys):
    ckpt = _checkpoint(tmp_path, _DUSt3R)
    args = ["run", "synthetic:loop:4:64x48", "--prior", "mast3r", "--quiet", "--out"]
    rc = main([*args, str(tmp_path / "o"), "--set", f"mast3r_prior.checkpoint={ckpt}"])
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "no descriptor heads" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "trajectory.txt").exists()


# -- keyframe features ----------------------------------------------------------------------


def test_keyframe_features_are_held_until_forgotten_and_others_dropped():
    prior, net = _prior()
    f = [_frame(i, 64, 48) for i in range(5)]
    encodes = lambda: net.calls.count("encode")
    prior.mono(f[0])
    prior.keep(f[0])  # keyframe 0: its features move out of the cache
    assert encodes() == 1 and len(prior.cache) == 0 and prior.kept[0][1] is not None
    prior.pair(f[1], f[0])
    prior.pair(f[1], f[0])
    assert encodes() == 2  # f1 once, f0 held
    prior.pair(f[2], f[0])  # f1 is no keyframe: dropped when f2 is encoded
    assert encodes() == 3 and [k[0] for k in prior.cache.keys()] == [2]
    prior.keep(f[2])
    prior.pair(f[3], f[2])
    prior.pair(f[3], f[0])
    assert encodes() == 4 and sorted(prior.kept) == [0, 2]
    prior.forget(0)
    prior.pair(f[3], f[0])  # no longer held: encoded again
    assert encodes() == 5 and sorted(prior.kept) == [2]
    prior.keep(f[4])  # marked before its first use: encoded once, straight into kept
    prior.pair(f[4], f[2])
    prior.pair(f[4], f[2])
    assert encodes() == 6 and prior.kept[4][1] is not None
    assert [k[0] for k in prior.cache.keys()] == [0]  # the last frame encoded unheld


def test_held_features_follow_the_image_content():
    prior, net = _prior()
    a = _frame(1, 64, 48)
    prior.keep(a)
    prior.mono(a)
    b = Frame(1, 1.0, 255 - a.rgb, None, None)  # same index, another image
    prior.mono(b)
    assert net.calls.count("encode") == 2
    prior.mono(a)
    assert net.calls.count("encode") == 2  # a still held


def test_without_keyframe_marks_features_stay_in_the_byte_bounded_cache():
    prior, net = _prior()
    f = [_frame(i, 64, 48) for i in range(3)]
    for j in (1, 2):
        prior.pair(f[j], f[0])
    assert net.calls.count("encode") == 3 and len(prior.cache) == 3 and not prior.kept


# -- settings -------------------------------------------------------------------------------


def test_settings_come_from_the_config_and_the_environment(tmp_path, monkeypatch):
    from mslam.config import load_config

    cfg = load_config(overrides=["mast3r_prior.size=224", "mast3r_prior.checkpoint=/w.pth"])
    m = cfg.mast3r_prior()
    assert (m.size, m.checkpoint, m.device) == (224, "/w.pth", "cpu")
    assert load_config().mast3r_prior() == Mast3rConfig()
    for bad, words in [("size=300", "224 or 512"), ("size=1024", "[224, 512]"),
                       ("cache_bytes=-1", "cache_bytes")]:  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(f"--set mast3r_prior.{bad}")) as exc:
            load_config(overrides=[f"mast3r_prior.{bad}"])
        assert words in str(exc.value)
    used = []
    monkeypatch.setattr(mast3r, "load_mast3r", lambda path, device: used.append(path))
    monkeypatch.setattr(mast3r, "Mast3rPrior", lambda model, cfg: SimpleNamespace(cfg=cfg))
    monkeypatch.setenv(mast3r.CHECKPOINT_ENV, "/env.pth")
    mast3r.load_prior(cfg=m)
    mast3r.load_prior(cfg=Mast3rConfig())
    mast3r.load_prior("/arg.pth", cfg=m)
    assert used == ["/w.pth", "/env.pth", "/arg.pth"]
    monkeypatch.delenv(mast3r.CHECKPOINT_ENV)
    with pytest.raises(FileNotFoundError, match=r"mast3r_prior\.checkpoint"):
        mast3r.load_prior()


def test_mast3r_extra_lists_the_modules_the_mast3r_code_imports():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extra = meta["optional-dependencies"]["mast3r"]
    assert {"einops", "huggingface_hub", "torch==2.13.0"} <= set(extra)
    assert any(d.startswith("pillow") for d in meta["dependencies"])
