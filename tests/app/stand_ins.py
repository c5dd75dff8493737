"""Stand-in networks for tests of the MASt3R adapter without torch or a checkpoint.

``StandInMast3r`` has upstream ``AsymmetricMASt3R``'s interface (``_encode_image``,
``_decoder``, ``_downstream_head``) on NumPy arrays and returns raw head outputs (use
``Mast3rConfig(apply_activations=True)`` with ``NumpyBackend``).
"""

from __future__ import annotations

import numpy as np


class StandInMast3r:
    """Mimics AsymmetricMASt3R's interface on NumPy arrays, returning raw head outputs."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.inputs: list[np.ndarray] = []  # the encoder's input images (1, 3, H, W)

    def _encode_image(self, img, true_shape):
        self.calls.append("encode")
        self.inputs.append(np.array(img))
        H, W = (int(x) for x in np.asarray(true_shape)[0])
        assert img.shape == (1, 3, H, W) and -1.0 <= img.min() and img.max() <= 1.0
        feat = img[:, :, ::16, ::16].reshape(1, 3, -1).transpose(0, 2, 1)  # (1, HW/256, 3)
        return feat, np.zeros((1, feat.shape[1], 2)), None

    def _decoder(self, f1, p1, f2, p2):
        self.calls.append("decode")
        return [f1, f1 + f2], [f2, f1 - f2]

    def _downstream_head(self, head, toks, shape):
        H, W = (int(x) for x in np.asarray(shape)[0])
        t = toks[-1][0].reshape(H // 16, W // 16, 3).repeat(16, 0).repeat(16, 1)
        g = np.linspace(-1, 1, H * W).reshape(H, W, 1)
        return {
            "pts3d": (t + np.array([0, 0, 1.0 + head]))[None],
            "conf": (t[..., 0] + head)[None],
            "desc": np.concatenate([t, g + t[..., :1]] * 6, axis=-1)[None],
            "desc_conf": t[..., 1][None],
        }
