"""MASt3R adapter — the real network behind the prior protocol (user's install and weights).

This project cannot ship MASt3R's 2.7 GB checkpoint; users who have it (and ``torch`` plus the
``naver/mast3r`` code on their path) get the genuine prior here. The adapter reproduces
upstream's calls (docs/upstream.md §2):

* the network input is upstream's: Pillow resize (LANCZOS shrinking, BICUBIC enlarging) and
  centre crop to 512 or 224 (``mslam.datasets.images.resize_img``), then ``[-1, 1]``
  normalisation in float32 (``mslam_ref.pointmap.network_input``), bit for bit;
* one encoder call per frame. Like upstream, which stores ``feat`` with each keyframe, the
  features of a frame marked with :meth:`Mast3rPrior.keep` are held until
  :meth:`Mast3rPrior.forget`; once the caller marks keyframes, the features of another frame
  last until the next frame that is not held is encoded (the current frame's only). A caller
  that marks none gets a byte-bounded cache (``cache``, ``Mast3rConfig.cache_bytes``);
* ``_decoder(feat1, pos1, feat2, pos2)`` and ``_downstream_head(1|2, tokens, true_shape)``.

Outputs are at the network resolution (e.g. 512 x 384 for 640 x 480 input); ``network_frame``
gives the matching resized frame and ``network_intrinsics`` the matching ``K``. Loading the
network and its one-line errors are in :mod:`mslam.priors.mast3r_load`; the settings
(checkpoint, input size, device, cache) come from the ``mast3r_prior`` config section, the
checkpoint also from ``$MSLAM_MAST3R_CHECKPOINT``.

The network is any object with upstream's interface, so tests use a stand-in; tensor handling
goes through a small *backend* (``TorchBackend`` by default, importing torch lazily). The
output activations (docs/upstream.md §2.1) are also given in NumPy form for stand-ins that
return raw head outputs (``Mast3rConfig.apply_activations``):

* ``pts3d = v / ‖v‖ · (exp(‖v‖) − 1)``, ``conf = 1 + exp(x)``, ``desc = d / ‖d‖``,
  ``desc_conf = exp(x)``.

Public names, in reading order:
    pts3d_activation, conf_activation, desc_activation, desc_conf_activation, postprocess,
    Mast3rConfig, TorchBackend, NumpyBackend, Mast3rUnavailable, load_mast3r, load_prior,
    Mast3rPrior
"""

from __future__ import annotations

import contextlib
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from mslam.datasets.frame import Frame
from mslam.datasets.images import resize_img
from mslam.priors.base import PairPrediction
from mslam.priors.cache import DEFAULT_CACHE_BYTES, ByteLRU
from mslam.priors.mast3r_load import INSTALL_HINT, Mast3rUnavailable, import_torch, load_mast3r
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import intrinsics_after_resize, network_input

__all__ = [
    "CHECKPOINT_ENV",
    "Mast3rConfig",
    "Mast3rPrior",
    "Mast3rUnavailable",
    "NumpyBackend",
    "TorchBackend",
    "conf_activation",
    "desc_activation",
    "desc_conf_activation",
    "load_mast3r",
    "load_prior",
    "postprocess",
    "pts3d_activation",
]


def pts3d_activation(v: FloatArray) -> FloatArray:
    """``v / ‖v‖ · (exp(‖v‖) − 1)`` per pixel (depth_mode 'exp'); 0 maps to 0.

    Upstream: dust3r/heads/postprocess.py::reg_dense_depth. Args: v (..., 3). Returns (..., 3).
    """
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0) * np.expm1(n)


def conf_activation(x: FloatArray) -> FloatArray:
    """``1 + exp(x)`` (conf_mode ('exp', 1, inf)); C >= 1. Upstream: postprocess.py::reg_dense_conf."""
    return 1.0 + np.exp(np.asarray(x, dtype=np.float64))


def desc_activation(d: FloatArray) -> FloatArray:
    """L2 normalisation of (..., F) descriptors. Upstream: mast3r/catmlp_dpt_head.py::postprocess."""
    d = np.asarray(d, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    return d / np.maximum(n, 1e-12)


def desc_conf_activation(x: FloatArray) -> FloatArray:
    """``exp(x)`` (desc_conf_mode ('exp', 0, inf)); Q > 0."""
    return np.exp(np.asarray(x, dtype=np.float64))


def postprocess(raw: dict[str, Any]) -> dict[str, FloatArray]:
    """Apply the four activations to raw head outputs with keys pts3d, conf, desc, desc_conf."""
    return {
        "pts3d": pts3d_activation(raw["pts3d"]),
        "conf": conf_activation(raw["conf"]),
        "desc": desc_activation(raw["desc"]),
        "desc_conf": desc_conf_activation(raw["desc_conf"]),
    }


@dataclass(frozen=True)
class Mast3rConfig:
    """Adapter settings (the ``mast3r_prior`` config section, ``SlamConfig.mast3r_prior``).

    Attributes:
        checkpoint: path of the checkpoint; "" takes ``$MSLAM_MAST3R_CHECKPOINT``.
        size: network resolution, 512 (long side) or 224 (short side + square crop).
        device: torch device string.
        apply_activations: the head returns raw values (True) or activated ones (False, as
            upstream's ``_downstream_head``).
        cache_bytes: bound of the encoder features of frames not marked with ``keep``
            (``mslam.priors.cache``).
    """

    checkpoint: str = ""
    size: int = 512
    device: str = "cpu"
    apply_activations: bool = False
    cache_bytes: int = DEFAULT_CACHE_BYTES

    def __post_init__(self) -> None:
        if self.size not in (224, 512):
            raise ValueError(f"size: must be 224 or 512, got {self.size}")
        if isinstance(self.cache_bytes, bool) or self.cache_bytes < 0:
            raise ValueError(f"cache_bytes: must be an int >= 0, got {self.cache_bytes!r}")


class TorchBackend:
    """Tensor handling with torch (imported on first use)."""

    def __init__(self, device: str = "cpu") -> None:
        self.torch = import_torch()
        self.device = device

    def to_tensor(self, a: np.ndarray):
        return self.torch.from_numpy(np.ascontiguousarray(a)).to(self.device)

    def to_numpy(self, t) -> np.ndarray:
        return t.detach().float().cpu().numpy().astype(np.float64)

    def as_float(self, t):
        return t.float()

    def no_grad(self):
        return self.torch.inference_mode()


class NumpyBackend:
    """Tensor handling for stand-in networks that work on NumPy arrays (tests, teaching)."""

    def to_tensor(self, a: np.ndarray) -> np.ndarray:
        return np.asarray(a)

    def to_numpy(self, t) -> np.ndarray:
        return np.asarray(t, dtype=np.float64)

    def as_float(self, t) -> np.ndarray:
        return np.asarray(t, dtype=np.float32)

    def no_grad(self):
        return contextlib.nullcontext()


#: Environment variable naming the checkpoint for :func:`load_prior`.
CHECKPOINT_ENV = "MSLAM_MAST3R_CHECKPOINT"


def load_prior(checkpoint: str | Path | None = None, cfg: Mast3rConfig | None = None):
    """A :class:`Mast3rPrior` on the user's checkpoint: the argument, else ``cfg.checkpoint``,
    else ``$MSLAM_MAST3R_CHECKPOINT``.

    Raises:
        FileNotFoundError: no checkpoint given or found. Mast3rUnavailable: torch, mast3r or
        one of its modules missing. ValueError: not a MASt3R checkpoint
        (:func:`mslam.priors.mast3r_load.load_mast3r`).
    """
    cfg = cfg or Mast3rConfig()
    checkpoint = checkpoint or cfg.checkpoint or os.environ.get(CHECKPOINT_ENV)
    if not checkpoint:
        raise FileNotFoundError(
            f"no MASt3R checkpoint: set mast3r_prior.checkpoint (--set "
            f"mast3r_prior.checkpoint=PATH) or {CHECKPOINT_ENV}=PATH; {INSTALL_HINT}"
        )
    return Mast3rPrior(load_mast3r(checkpoint, cfg.device), cfg)


class Mast3rPrior:
    """The prior protocol on top of a MASt3R network (module docstring).

    Args:
        model: object with ``_encode_image``, ``_decoder``, ``_downstream_head``.
        cfg: adapter settings.
        backend: tensor backend; default :class:`TorchBackend` on ``cfg.device``.
    """

    #: Pointmaps at a scale of their own, not metres (mslam.system.global_opt.Backend.spread_depths).
    metric: ClassVar[bool] = False

    def __init__(self, model, cfg: Mast3rConfig = Mast3rConfig(), backend=None) -> None:
        for name in ("_encode_image", "_decoder", "_downstream_head"):
            if not callable(getattr(model, name, None)):
                raise ValueError(f"model: missing method {name} of the MASt3R interface")
        self.model = model
        self.cfg = cfg
        self.backend = backend if backend is not None else TorchBackend(cfg.device)
        #: Encoder features ``(feat, pos, true_shape)`` of frames not marked with ``keep``,
        #: bounded in bytes (only the current frame's once the caller marks keyframes).
        self.cache = ByteLRU(cfg.cache_bytes)
        #: Frame index -> (content key, features or None until first encoded) of keyframes.
        self.kept: dict[int, tuple[tuple, Any]] = {}
        self._marks_keyframes = False
        self._lock = threading.Lock()  # keep/forget may come from another thread than pair

    def network_frame(self, frame: Frame) -> Frame:
        """The frame resized and cropped to the network resolution (depth dropped)."""
        img, _ = resize_img(frame.rgb, self.cfg.size)
        return Frame(frame.index, frame.timestamp, img, None, frame.T_WC)

    def network_intrinsics(self, K: FloatArray, frame: Frame) -> FloatArray:
        """``K`` of the network-resolution image (docs/upstream.md §10.2, plain multiplication)."""
        _, tr = resize_img(frame.rgb, self.cfg.size)
        return intrinsics_after_resize(K, tr)

    @staticmethod
    def _key(frame: Frame) -> tuple:
        return (int(frame.index), frame.rgb.shape, hash(frame.rgb.tobytes()))

    def keep(self, frame: Frame) -> None:
        """Hold ``frame``'s encoder features while it is a keyframe (until :meth:`forget`).

        Upstream keeps ``feat`` with every keyframe in its keyframe buffer. Call it when the
        frame becomes a keyframe; its features move out of ``cache`` (or are encoded at its
        next use). From the first call on, the features of a frame that is not held last only
        until the next such frame is encoded, as upstream's per-frame ``feat``.
        """
        key = self._key(frame)
        with self._lock:
            self._marks_keyframes = True
            held = self.kept.get(key[0])
            if held is None or held[0] != key:
                self.kept[key[0]] = (key, self.cache.pop(key))

    def forget(self, frame_index: int) -> None:
        """Drop the features held for frame ``frame_index`` (it is no longer a keyframe)."""
        with self._lock:
            self.kept.pop(int(frame_index), None)

    def _encode(self, frame: Frame):
        """``(feat, pos, true_shape)`` of a frame, encoded once while it is held or cached."""
        key = self._key(frame)
        with self._lock:
            held = self.kept.get(key[0])
            if held is not None and held[0] == key and held[1] is not None:
                return held[1]
            if key in self.cache:
                return self.cache.get(key, lambda: None)
        enc = self._encoder(frame)
        with self._lock:
            held = self.kept.get(key[0])
            if held is not None and held[0] == key:
                self.kept[key[0]] = (key, enc)
            else:
                if self._marks_keyframes:
                    self.cache.clear()  # the previous frame's features: not a keyframe
                self.cache.put(key, enc)
        return enc

    def _encoder(self, frame: Frame):
        """``(feat, pos, true_shape)`` of upstream's ``_encode_image`` on the network input."""
        img, _ = resize_img(frame.rgb, self.cfg.size)
        H, W = img.shape[:2]
        b = self.backend
        shape = b.to_tensor(np.array([[H, W]], dtype=np.int32))
        with b.no_grad():
            feat, pos, _ = self.model._encode_image(b.to_tensor(network_input(img)), shape)
        return feat, pos, shape

    def _decode(self, enc1, enc2):
        """Upstream mast3r_utils.py::decoder: both heads on float tokens."""
        (f1, p1, s1), (f2, p2, s2) = enc1, enc2
        b = self.backend
        with b.no_grad():
            dec1, dec2 = self.model._decoder(f1, p1, f2, p2)
            res1 = self.model._downstream_head(1, [b.as_float(t) for t in dec1], s1)
            res2 = self.model._downstream_head(2, [b.as_float(t) for t in dec2], s2)
        return self._numpy(res1), self._numpy(res2)

    def _numpy(self, res) -> dict[str, FloatArray]:
        out = {k: self.backend.to_numpy(res[k])[0] for k in ("pts3d", "conf", "desc", "desc_conf")}
        return postprocess(out) if self.cfg.apply_activations else out

    def mono(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """Upstream mast3r_inference_mono: decode (f, f), keep view 1. Shapes at network size."""
        enc = self._encode(frame)
        res11, _ = self._decode(enc, enc)
        return res11["pts3d"], res11["conf"]

    def pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        """Upstream mast3r_asymmetric_inference: ``res11, res21 = decoder(i, j)``."""
        r1, r2 = self._decode(self._encode(frame_i), self._encode(frame_j))
        return PairPrediction(
            r1["pts3d"], r1["conf"], r1["desc"], r1["desc_conf"],
            r2["pts3d"], r2["conf"], r2["desc"], r2["desc_conf"],
        )  # fmt: skip
