"""Synthetic sequences — exact RGB-D frames of a ``mslam_ref.synthetic`` scene along a path.

The built-in data of the project (demos, tests, tutorials): the procedural room of
``mslam_ref.synthetic`` rendered frame by frame along a named camera path, with ground-truth
camera-to-world poses.
The synthetic prior (``mslam.priors.synthetic``) turns these frames into noisy
MASt3R-like pointmaps.

Quick use::

    seq = make_sequence("loop", n_frames=80, width=160, height=120, seed=0)
    f = seq[0]          # Frame: rgb (H,W,3) uint8, depth (H,W) metres, T_WC (8,) Sim(3)
    seq.K               # (3, 3) intrinsics, principal point at ((W-1)/2, (H-1)/2)

Public names, in reading order:
    DEFAULT_SYNTHETIC, parse_synthetic, SyntheticSequence, make_sequence (and PATHS, the
    accepted path names)
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from mslam.datasets.frame import Frame, FrameSequence
from mslam_ref.conventions import FloatArray
from mslam_ref.synthetic import (
    PATHS,
    Scene,
    camera_path,
    check_synthetic_size,
    intrinsics,
    make_scene,
    render,
)

__all__ = ["DEFAULT_SYNTHETIC", "PATHS", "SyntheticSequence", "make_sequence", "parse_synthetic"]

#: The built-in sequence of ``mslam run --out DIR`` (name, frames, width, height).
DEFAULT_SYNTHETIC = ("loop", 72, 128, 96)


def parse_synthetic(source: str) -> tuple[str, int, int, int]:
    """``synthetic:NAME[:FRAMES[:WxH]]`` → (name, frames, width, height); defaults from
    :data:`DEFAULT_SYNTHETIC`.

    Raises:
        ValueError: a malformed source, fewer than 2 frames or fewer than 16x16 pixels.
    """
    parts = source.split(":")
    name = parts[1] if len(parts) > 1 and parts[1] else DEFAULT_SYNTHETIC[0]
    n, w, h = DEFAULT_SYNTHETIC[1:]
    try:
        if len(parts) > 2:
            n = int(parts[2])
        if len(parts) > 3:
            w, h = (int(x) for x in parts[3].lower().split("x"))
        if len(parts) > 4:
            raise ValueError
    except ValueError:
        raise ValueError(f"SOURCE {source!r}: expected synthetic:NAME[:FRAMES[:WxH]]") from None
    if n < 2 or w < 16 or h < 16:
        raise ValueError(f"SOURCE {source!r}: need >= 2 frames and >= 16x16 pixels")
    check_synthetic_size(n, w, h, f"SOURCE {source!r}")
    return name, n, w, h


class SyntheticSequence(FrameSequence):
    """A rendered sequence: frames are ray-cast on demand (and a few are cached).

    Attributes (besides :class:`~mslam.datasets.frame.FrameSequence`'s):
        scene: the :class:`Scene`.
        path: the camera-path name.
        width, height: image size.
        seed: the seed of scene and path.
        fps: frame rate used for timestamps ``i / fps``.
    """

    T_WC: FloatArray
    K: FloatArray

    def __init__(
        self,
        path: str,
        scene: Scene,
        T_WC: FloatArray,
        K: FloatArray,
        width: int,
        height: int,
        seed: int,
        fps: float = 30.0,
    ) -> None:
        self.path = path
        self.name = f"synthetic:{path}"
        self.scene = scene
        self.T_WC = np.asarray(T_WC, dtype=np.float64)
        self.K = np.asarray(K, dtype=np.float64)
        self.width, self.height = int(width), int(height)
        self.seed = int(seed)
        self.fps = float(fps)
        self.has_depth = True
        self.timestamps = np.arange(len(self.T_WC), dtype=np.float64) / self.fps
        self._cache: OrderedDict[int, Frame] = OrderedDict()

    def render(self, i: int) -> tuple[np.ndarray, FloatArray, np.ndarray]:
        """Render frame ``i``: rgb (H, W, 3) uint8, depth (H, W) metres, surface ids (H, W)."""
        return render(self.scene, self.T_WC[i], self.K, self.width, self.height)

    def _load(self, i: int) -> Frame:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        rgb, depth, _ = self.render(i)
        rgb.flags.writeable = False
        depth.flags.writeable = False
        T = self.T_WC[i].copy()
        T.flags.writeable = False
        frame = Frame(index=i, timestamp=float(self.timestamps[i]), rgb=rgb, depth=depth, T_WC=T)
        self._cache[i] = frame
        if len(self._cache) > 16:
            self._cache.popitem(last=False)
        return frame


def make_sequence(
    name: str = "loop",
    n_frames: int = 80,
    width: int = 160,
    height: int = 120,
    seed: int = 0,
    fov_deg: float = 70.0,
) -> SyntheticSequence:
    """A synthetic RGB-D sequence with ground truth: room from ``seed``, path ``name``.

    Args:
        name: camera path, one of :data:`PATHS` (``loop``, ``jump``, ``detour``, ``rotation``,
            ``forward``).
        n_frames: number of frames (2 to ``mslam_ref.synthetic.MAX_FRAMES``).
        width, height: image size in pixels (at most ``mslam_ref.synthetic.MAX_PIXELS``).
        seed: seed of the scene and of the path's small variations (deterministic).
        fov_deg: horizontal field of view.

    Returns:
        a :class:`SyntheticSequence`; ``seq[i]`` renders frame i.
    """
    if name.startswith("synthetic:"):
        name = name.split(":", 1)[1]
    check_synthetic_size(n_frames, width, height, f"synthetic:{name}")
    T_WC = camera_path(name, n_frames, seed)
    K = intrinsics(width, height, fov_deg)
    return SyntheticSequence(name, make_scene(seed), T_WC, K, width, height, seed)
