"""RGB-D prior — MASt3R-like predictions for real RGB-D frames, without ground truth.

For a real sequence with a depth camera (TUM, 7-Scenes), the pointmap of image i in its own
camera is the back-projected depth, ``X_ii = z · K⁻¹[u, v, 1]``. The second pointmap needs the
pose that carries camera j into camera i, and this prior estimates it the classical way, from
the two images only (never from ground truth):

1. SIFT (or ORB) keypoints in both grey images (upscaled to ``detect_min_width`` when the frame
   is small), ratio-test matches j → i, kept only where the keypoint of i is claimed once;
2. 3-D points of j's keypoints from j's depth, with i's keypoints as 2-D observations;
3. ``cv2.solvePnPRansac`` (EPnP, then the iterative solver if EPnP's answer fails the sanity
   check: finite, ``|t| <= max_translation``, inliers in front of camera i and reprojecting
   within ``ransac_px`` after ``cv2.solvePnPRefineLM``) give ``T_ij`` (``X_i = R X_j + t``);
4. point-to-plane ICP of j's depth points onto i's depth map refines it (``icp_*``), kept only
   while it still explains the feature matches (ICP alone can slide along a plane).

``X_ji = T_ij · X_jj``. Confidences: valid depth ``C = 1 + conf_max · exp(-σ(z)/conf_sigma)``
with the Kinect noise model ``σ(z) = 0.0012 + 0.0019 (z - 0.4)²`` (Nguyen et al. 2012); pixels
without depth are filled from the nearest valid pixel (or ``fill_depth``) and get ``C = 1``.
For ``C_ji``, pixels of j whose point disagrees with i's depth (occluded or wrong) or falls
outside image i are pulled towards 1 (``inconsistent_factor``, ``covis_factor``); if the pose
estimate failed (fewer than ``min_inliers``), ``C_ji = 1`` and ``Q_ji = FAILED_Q`` (0.01)
everywhere, so that no correspondence of the pair passes upstream's ``Q_conf`` gate.
Descriptors and Q come from image patches (``descriptors.patch_descriptors``), as in the
synthetic prior.

Frames of any resolution work: ``K`` is given at the sequence's native size and rescaled to the
frame's size (``pointmap.scale_intrinsics``).

Public names, in reading order:
    FAILED_Q, RGBDPriorConfig, RGBDPrior, fill_depth
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from contextlib import contextmanager
from typing import ClassVar

import cv2
import numpy as np

from mslam.datasets.frame import Frame
from mslam.priors import rgbd_pose as pose
from mslam.priors.base import PairPrediction
from mslam.priors.cache import ByteLRU
from mslam.priors.descriptors import descriptor_Q, patch_descriptors
from mslam.priors.keypoints import detect, ratio_matches
from mslam.priors.rgbd_config import RGBDPriorConfig
from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import camera_rays, scale_intrinsics

__all__ = ["FAILED_Q", "RGBDPrior", "RGBDPriorConfig", "fill_depth"]

#: Descriptor confidence ``Q_ji`` of a pair whose pose estimate failed: ``sqrt(Q_ii · Q_ji)``
#: stays far below upstream's ``Q_conf = 1.5`` for any ``Q_ii <= 1 + q_gain``.
FAILED_Q = 0.01


def fill_depth(depth: FloatArray, default: float = 3.0) -> tuple[FloatArray, np.ndarray]:
    """Fill invalid (<= 0) depth from the nearest valid pixel (OpenCV's 5x5-mask Euclidean
    distance transform with labels: within 2 % of the exact nearest distance; scipy's exact
    transform took 12 ms at 512x384, this 2 ms).

    Args:
        depth: (H, W) metres, 0 where invalid.
        default: value used when no pixel is valid.

    Returns:
        filled (H, W) depth and the (H, W) validity mask of the input.
    """
    valid = depth > 0
    if not valid.any():
        return np.full(depth.shape, float(default)), valid
    if valid.all():
        return depth.copy(), valid
    # DIST_LABEL_PIXEL numbers the valid (zero) pixels 1, 2, ... in row-major order.
    _, label = cv2.distanceTransformWithLabels(
        (~valid).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    return depth[valid][label - 1], valid


def _depth(frame: Frame) -> FloatArray:
    """The frame's (H, W) depth; a ValueError naming the frame when it has none."""
    if frame.depth is None:
        raise ValueError(f"frame {frame.index}: the RGB-D prior needs a depth image")
    return frame.depth


def _kinect_sigma(z: FloatArray) -> FloatArray:
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


class RGBDPrior:
    """MASt3R stand-in for real RGB-D frames (module docstring).

    Args:
        sequence: provides ``K`` at its frames' size (``width``/``height`` attributes, else the
            first frame's shape) and must have depth.
        cfg: parameters.

    Use :meth:`from_intrinsics` to build one from ``K`` and an image size instead.
    """

    #: Pointmaps in metres (made from depth): a keyframe's Sim(3) scale alone is the map's
    #: scale drift (mslam.system.global_opt.Backend.spread_depths).
    metric: ClassVar[bool] = True

    def __init__(
        self,
        sequence,
        cfg: RGBDPriorConfig = RGBDPriorConfig(),  # noqa: B008 (frozen, immutable)
    ) -> None:
        if sequence.K is None or not sequence.has_depth:
            raise ValueError(f"sequence: {sequence.name} needs intrinsics and depth for RGB-D")
        if getattr(sequence, "width", None) and getattr(sequence, "height", None):
            size = (int(sequence.width), int(sequence.height))
        else:
            H, W = sequence[0].shape
            size = (W, H)
        self._setup(sequence.K, size, cfg)

    @classmethod
    def from_intrinsics(
        cls,
        K: FloatArray,
        image_size: tuple[int, int],
        cfg: RGBDPriorConfig = RGBDPriorConfig(),  # noqa: B008 (frozen, immutable)
    ) -> RGBDPrior:
        """Build from ``K`` (3, 3) valid at ``image_size = (W, H)``."""
        obj = object.__new__(cls)
        obj._setup(K, image_size, cfg)
        return obj

    def _setup(self, K: FloatArray, image_size: tuple[int, int], cfg: RGBDPriorConfig) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.cfg = cfg
        self.last_inliers = 0
        #: Wall seconds per sub-step (``features``, ``ratio``, ``pnp``, ``icp``, ``depth``,
        #: ``descriptors``, ``consistency``), for the profiles in benchmarks/.
        self.seconds: defaultdict[str, float] = defaultdict(float)
        #: Per-frame results (features, depth views, descriptors), bounded in bytes.
        self.cache = ByteLRU(cfg.desc.cache_bytes)
        self._rays_by_shape: dict[tuple[int, int], FloatArray] = {}
        self._hashes: dict[int, int] | None = None  # image content hashes during a pair call
        self._prefetched: tuple[int, Callable[..., None]] | None = None  # (frame index, join)
        self._seconds_lock = threading.Lock()  # the prefetch worker times its steps too

    @contextmanager
    def _timed(self, step: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            with self._seconds_lock:
                self.seconds[step] += time.perf_counter() - t0

    def _key(self, kind: str, frame: Frame) -> tuple:
        h = self._hashes.get(id(frame.rgb)) if self._hashes else None
        if h is None:
            h = hash(frame.rgb.tobytes())
        return (kind, int(frame.index), frame.rgb.shape, h)

    def _cached(self, kind: str, frame: Frame, fn):
        """Per-frame results (features, descriptors) keyed by index and image content."""
        return self.cache.get(self._key(kind, frame), lambda: fn(frame))

    def K_for(self, frame: Frame) -> FloatArray:
        """Intrinsics at the frame's resolution."""
        H, W = frame.shape
        if (W, H) == self.image_size:
            return self.K
        return scale_intrinsics(self.K, self.image_size, (W, H))

    # -- geometry ----------------------------------------------------------------------------
    def _features(self, frame: Frame):
        with self._timed("features"):
            return self._detect(frame)

    def _detect(self, frame: Frame):
        return detect(frame.rgb, self.cfg)

    def relative_pose(self, frame_i: Frame, frame_j: Frame) -> tuple[FloatArray, int]:
        """Estimate ``T_ij`` (camera j → camera i) from the images and j's depth.

        Returns:
            T_ij: (8,) Sim(3) with s = 1 (identity when the estimate failed).
            n_inliers: PnP inliers (< ``min_inliers`` means failure).
        """
        cfg = self.cfg
        self._settle(frame_i, frame_j)
        if frame_j.depth is None:
            raise ValueError("frame_j: the RGB-D prior needs a depth image")
        uv_i, d_i = self._cached("features", frame_i, self._features)
        uv_j, d_j = self._cached("features", frame_j, self._features)
        if d_i is None or d_j is None or len(uv_i) < 2 or len(uv_j) < 2:
            return sim3.identity(), 0
        with self._timed("ratio"):
            qj, ti = ratio_matches(d_j, d_i, cfg.ratio)
        if len(qj) < cfg.min_inliers:
            return sim3.identity(), 0
        # One-to-one: a keypoint of i claimed by several keypoints of j is ambiguous. On blurred
        # frames one featureless keypoint can attract dozens of matches, which RANSAC then
        # "explains" with a camera 1e13 m away (every point projects onto that pixel).
        _, inv, counts = np.unique(ti, return_inverse=True, return_counts=True)
        once = counts[inv] == 1
        qj, ti = qj[once], ti[once]
        if len(qj) < cfg.min_inliers:
            return sim3.identity(), 0
        H, W = frame_j.shape
        uj = np.clip(np.round(uv_j[qj]), 0, [W - 1, H - 1]).astype(np.int64)
        z = frame_j.depth[uj[:, 1], uj[:, 0]]
        ok = z > 0
        if ok.sum() < cfg.min_inliers:
            return sim3.identity(), 0
        Kj, Ki = self.K_for(frame_j), self.K_for(frame_i)
        rays = np.stack(
            [
                (uv_j[qj, 0] - Kj[0, 2]) / Kj[0, 0],
                (uv_j[qj, 1] - Kj[1, 2]) / Kj[1, 1],
                np.ones(len(z)),
            ],
            -1,
        )
        obj = (rays * z[:, None])[ok]
        img = uv_i[ti][ok]
        for flags in (cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE):
            with self._timed("pnp"):
                T_ij, n = pose.pnp(obj, img, Ki, flags, cfg)
            if n >= cfg.min_inliers:
                with self._timed("icp"):
                    target = self._icp_target(frame_i)
                    T_icp = pose.refine_icp(frame_i.depth, frame_j.depth, Ki, Kj, T_ij, cfg, target)
                    return pose.icp_agrees(T_icp, T_ij, obj, img, Ki, cfg), n
        return sim3.identity(), n

    def _icp_target(self, frame_i: Frame):
        """``rgbd_pose.icp_target`` of frame i, once per frame (a frame is i of its tracking
        pair and of the graph edges it takes part in)."""
        if self.cfg.icp_iters <= 0 or frame_i.depth is None:
            return None

        def target(f: Frame) -> tuple[FloatArray, np.ndarray]:
            # The filled depth's points: ICP reads only those of valid pixels.
            return pose.icp_target(_depth(f), self.K_for(f), self._view(f)[0])

        return self._cached("icp_target", frame_i, target)

    # -- protocol ----------------------------------------------------------------------------
    def _view(self, frame: Frame) -> tuple[FloatArray, FloatArray, np.ndarray]:
        return self._cached("view", frame, self._compute_view)

    def _compute_view(self, frame: Frame) -> tuple[FloatArray, FloatArray, np.ndarray]:
        with self._timed("depth"):
            return self._depth_view(frame)

    def _depth_view(self, frame: Frame) -> tuple[FloatArray, FloatArray, np.ndarray]:
        z, valid = fill_depth(_depth(frame), self.cfg.fill_depth)
        X = z[..., None] * self._rays(frame)  # pointmap.backproject with the rays kept
        C = np.where(
            valid, 1.0 + self.cfg.conf_max * np.exp(-_kinect_sigma(z) / self.cfg.conf_sigma), 1.0
        )
        for a in (X, C, valid):
            a.setflags(write=False)  # cached and shared by every pair of this frame
        return X, C, valid

    def _rays(self, frame: Frame) -> FloatArray:
        """``pointmap.camera_rays`` at the frame's size, computed once per size."""
        if frame.shape not in self._rays_by_shape:
            rays = camera_rays(self.K_for(frame), *frame.shape)
            rays.setflags(write=False)
            self._rays_by_shape[frame.shape] = rays
        return self._rays_by_shape[frame.shape]

    def _desc(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """``D`` (H, W, F) and ``Q`` (H, W) (``descriptors.descriptor_Q``)."""
        return self._cached("desc", frame, self._patch_descriptors)

    def _patch_descriptors(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        with self._timed("descriptors"):
            D, contrast = patch_descriptors(frame.rgb, self.cfg.desc)
            Q = descriptor_Q(contrast, self.cfg.q_gain, self.cfg.q_contrast)
            for a in (D, Q):
                a.setflags(write=False)  # cached and shared by every pair of this frame
            return D, Q

    def mono(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """``X_ii (H, W, 3)`` from the (filled) depth and ``C_ii (H, W)``."""
        self._settle(frame)
        X, C, _ = self._view(frame)
        return X, C

    def pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        """Both pointmaps in camera i, with the relative pose from features + depth + PnP.

        Sets ``self.last_inliers`` to the PnP inlier count of this pair.
        """
        # The cache keys hash each image's content: once per image for the whole pair, not at
        # each of the ~10 lookups (0.14 ms each at 512x384). Any other caller hashes anew.
        self._settle(frame_i, frame_j)
        self._hashes = {id(f.rgb): hash(f.rgb.tobytes()) for f in (frame_i, frame_j)}
        try:
            return self._pair(frame_i, frame_j)
        finally:
            self._hashes = None

    def _pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        # Keypoints, then descriptors, of the frames that have none cached, on a worker thread
        # (OpenCV releases the GIL): the single-threaded steps of the pose (ratio test, PnP,
        # ICP) run beside the descriptors instead of after them (docs/system.md).
        frames = (frame_i, frame_j)
        keys = [self._key("features", f) for f in frames]
        jobs = {k: (lambda f=f: self._features(f)) for k, f in zip(keys, frames, strict=True)}
        for f in frames:
            jobs[self._key("desc", f)] = lambda f=f: self._patch_descriptors(f)
        join = self.cache.compute_alongside(jobs)
        X_ii, C_ii, valid_i = self._view(frame_i)
        X_jj, C_jj, _ = self._view(frame_j)
        join(*keys)
        T_ij, n = self.relative_pose(frame_i, frame_j)
        self.last_inliers = n
        # sim3.act for one pose and H·W points, as one (3, 3) product: s R X + t.
        sR = T_ij[7] * so3.to_matrix(T_ij[3:7])
        X_ji = (X_jj.reshape(-1, 3) @ sR.T + T_ij[:3]).reshape(X_jj.shape)
        if n >= self.cfg.min_inliers:
            with self._timed("consistency"):
                C_ji = pose.consistency(
                    X_ji, C_jj, _depth(frame_i), valid_i, self.K_for(frame_i), self.cfg
                )
        join()
        D_ii, Q_ii = self._desc(frame_i)
        D_jj, Q_jj = self._desc(frame_j)
        if n < self.cfg.min_inliers:
            # No pose: X_ji is j's pointmap left in camera j, so every correspondence the
            # matcher would find is a guess. C_ji = 1 and a descriptor confidence so low that
            # the match quality sqrt(Q_ii Q_ji) stays below upstream's Q_conf gate make
            # tracking, edges and relocalisation reject the pair instead of building on it.
            C_ji = np.ones_like(C_jj)
            Q_jj = np.full_like(Q_jj, FAILED_Q)
        return PairPrediction(X_ii, C_ii, D_ii, Q_ii, X_ji, C_ji, D_jj, Q_jj)

    # -- prefetch ----------------------------------------------------------------------------
    @property
    def prefetching(self) -> bool:
        """Whether :meth:`prefetch` does anything (``cfg.prefetch``)."""
        return self.cfg.prefetch

    def prefetch(self, frame: Frame, partner: Frame | None = None) -> None:
        """Start ``frame``'s own work (keypoints, descriptors, depth view, ICP target: nothing
        that depends on a keyframe, so ``partner`` is not used) on a worker thread; the same
        functions as on demand, so the same values. They enter the cache when a pair or view
        of that frame is asked for, or at the next :meth:`prefetch` or :meth:`join_prefetch`."""
        self.join_prefetch()
        if not self.cfg.prefetch:
            return
        key = lambda kind: self._key(kind, frame)
        view = self.cache.peek(key("view"))
        held: dict[str, tuple] = {}

        def compute_view() -> tuple:
            held["view"] = self._compute_view(frame)
            return held["view"]

        jobs = {
            key("features"): lambda: self._features(frame),
            key("view"): compute_view,
            key("desc"): lambda: self._patch_descriptors(frame),
        }
        depth = frame.depth
        if self.cfg.icp_iters > 0 and depth is not None:
            K = self.K_for(frame)
            jobs[key("icp_target")] = lambda: pose.icp_target(depth, K, held.get("view", view)[0])
        self._prefetched = (int(frame.index), self.cache.compute_alongside(jobs))

    def join_prefetch(self) -> None:
        """Wait for the prefetch in flight, if any, and cache its results. A failed step is
        dropped: it runs again, and raises, when its result is asked for."""
        pending, self._prefetched = self._prefetched, None
        if pending is not None:
            with contextlib.suppress(Exception):
                pending[1]()

    def _settle(self, *frames: Frame) -> None:
        """Join the prefetch when it is working on one of ``frames``."""
        if self._prefetched and any(int(f.index) == self._prefetched[0] for f in frames):
            self.join_prefetch()
