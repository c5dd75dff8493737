"""Synthetic data — procedural textured rooms, named camera paths, exact RGB-D sequences.

The built-in data of the project (demos, tests, tutorials): a closed room with textured walls,
floor and ceiling, boxes and spheres (texture, occlusions, depth edges), rendered by exact ray
casting in vectorised NumPy at any resolution, with ground-truth camera-to-world poses.
The synthetic prior (``mslam_ref.priors.synthetic``) turns these frames into noisy
MASt3R-like pointmaps.

Quick use::

    seq = make_sequence("loop", n_frames=80, width=160, height=120, seed=0)
    f = seq[0]          # Frame: rgb (H,W,3) uint8, depth (H,W) metres, T_WC (8,) Sim(3)
    seq.K               # (3, 3) intrinsics, principal point at ((W-1)/2, (H-1)/2)

Public names, in reading order:
    SyntheticSequence, make_sequence, intrinsics, PATHS, camera_path, jump_indices,
    Scene, make_scene, cast_rays, render
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from mslam_ref.conventions import FloatArray
from mslam_ref.datasets.frame import Frame, FrameSequence
from mslam_ref.synthetic.paths import PATHS, camera_path, jump_indices
from mslam_ref.synthetic.scene import Scene, cast_rays, make_scene, render

__all__ = [
    "MAX_FRAMES",
    "MAX_PIXELS",
    "PATHS",
    "Scene",
    "SyntheticSequence",
    "camera_path",
    "cast_rays",
    "check_synthetic_size",
    "intrinsics",
    "jump_indices",
    "make_scene",
    "make_sequence",
    "render",
]


#: Largest synthetic sequence (frames) and frame (pixels): the poses and the vectorised ray
#: casting allocate in proportion, so larger requests are refused before any allocation.
MAX_FRAMES = 100_000
MAX_PIXELS = 2048 * 1536


def check_synthetic_size(n_frames: int, width: int, height: int, what: str = "synthetic") -> None:
    """``ValueError`` naming ``what`` unless 2 <= frames <= MAX_FRAMES and W·H <= MAX_PIXELS."""
    if not 2 <= int(n_frames) <= MAX_FRAMES:
        raise ValueError(f"{what}: frames must be in [2, {MAX_FRAMES}] (the cap), got {n_frames}")
    if int(width) * int(height) > MAX_PIXELS:
        raise ValueError(
            f"{what}: {width}x{height} is larger than the cap of {MAX_PIXELS} pixels "
            "(e.g. 2048x1536)"
        )


def intrinsics(width: int, height: int, fov_deg: float = 70.0) -> FloatArray:
    """Pinhole intrinsics with horizontal field of view ``fov_deg`` and square pixels.

    ``fx = fy = (W / 2) / tan(fov / 2)``, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2`` (the centre
    of the image under the pixel-centre convention, as upstream's re-centred ``K_opt``).

    Returns:
        (3, 3) float64.
    """
    if int(width) < 2 or int(height) < 2:
        raise ValueError(f"width, height: must be >= 2, got {width}x{height}")
    if not 1.0 < fov_deg < 170.0:
        raise ValueError(f"fov_deg: must be in (1, 170), got {fov_deg}")
    f = (width / 2.0) / np.tan(np.deg2rad(fov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


class SyntheticSequence(FrameSequence):
    """A rendered sequence: frames are ray-cast on demand (and a few are cached).

    Attributes (besides :class:`~mslam_ref.datasets.frame.FrameSequence`'s):
        scene: the :class:`Scene`.
        path: the camera-path name.
        width, height: image size.
        seed: the seed of scene and path.
        fps: frame rate used for timestamps ``i / fps``.
    """

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
        name: camera path, one of :data:`PATHS` (``loop``, ``jump``, ``rotation``, ``forward``).
        n_frames: number of frames (2 to :data:`MAX_FRAMES`).
        width, height: image size in pixels (at most :data:`MAX_PIXELS`).
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
