"""Two-view prior — MASt3R-like pointmaps from two RGB images by classical geometry.

For RGB-only input without a network (image folders, videos, the RGB stream of TUM/7-Scenes),
``pair(i, j)`` reconstructs both images in camera i from the images alone
(:mod:`mslam.priors.twoview_geometry` has the maths):

1. dense flow ``F_ij``, ``F_ji`` (DIS at half or full resolution, :mod:`twoview_dis`) with a
   forward–backward check (``fb_px``), seeded by a SIFT homography when that is more
   consistent (:mod:`mslam.priors.twoview_flow`: DIS alone follows ~10-15 px at 160x120);
2. relative pose ``X_j = R_ji X_i + t_ji`` from the essential matrix (RANSAC on at most
   ``max_ransac_points`` correspondences on a regular grid with forward–backward error below
   ``pose_fb_px``), refined on all its inliers (robust Sampson least squares), together with
   the homography's decompositions; hypotheses the pair cannot tell apart (a planar scene)
   are resolved by an earlier reconstruction of i or j (:mod:`mslam.priors.twoview_planar`);
3. the pair is **degenerate** — too few inliers (``min_inliers``) or consistent flow vectors
   (``min_flow_frac``), or too little parallax (:func:`homography_parallax` <
   ``min_parallax_px``: the flow is a homography that is a rotation, which covers pure
   rotation and a tiny baseline, but not a plane seen from two centres) — then no geometry is
   invented: the pointmaps are fronto-parallel planes, ``C = 1`` everywhere and ``Q_ji = FAILED_Q``, so the match quality ``sqrt(Q_ii Q_ji)``
   stays under upstream's ``Q_conf`` and tracking, edges and relocalisation reject the pair;
4. otherwise every pixel of i and of j is triangulated in camera i (midpoint) along its
   symmetric flow (:func:`symmetric_flow`: one correspondence per point); pixels that fail
   (occlusion, cheirality, flow leaving the image) get the depth of the nearest triangulated
   pixel and ``C = 1`` (``NO_INFO_C``: fusion and the export leave them out);
5. the scale is arbitrary (``‖t_ji‖ = 1``) and normalised as MASt3R's outputs: both pointmaps
   are divided by the median distance of their triangulated points to camera i's centre;
6. ``C = 1 + conf_max · w_θ · w_r · w_fb`` with ``w_θ = 1 - exp(-(θ/angle_sigma)²)``
   (triangulation angle θ), ``w_r = exp(-(r/reproj_sigma)²)`` (reprojection error r, pixels)
   and ``w_fb = exp(-(e_fb/fb_sigma)²)`` (flow consistency). On the 7-Scenes kitchen
   (2026-11-26) the depth error falls with C (median 16 % at C <= 1.5, 6–7 % above 16), almost
   all of it through ``w_θ``: ``e_fb`` and ``r`` are uncorrelated with it (docs/evaluation.md);
7. descriptors ``D`` and ``Q = 1 + q_gain tanh(contrast/q_contrast)`` are the patch
   descriptors of the RGB-D prior (``descriptors.patch_descriptors``, ``descriptor_Q``).

Intrinsics: ``K`` when calibrated (``--calib``), else :func:`focal_guess_intrinsics` (60°
across the long side) times ``focal_scale`` (set from the video where it determines it,
:mod:`twoview_selfcal`, :mod:`twoview_focal`), which the SLAM system never sees: uncalibrated,
it only uses the pointmaps, as with MASt3R. Uncalibrated, a pair is without parallax when its
flow is a rotation for *some* focal length (``focal_free_parallax``, :mod:`twoview_homography`).

``mono(i)``: no parallax, no honest depth: the latest non-degenerate two-view pointmap of the
image (as i or j, in its own camera, normalised), else a fronto-parallel plane at distance 1,
``C = 1``. The frontend does not start from ``mono`` (``needs_parallax = True``): it waits for
a pair with parallax, or starts under pure rotation (:mod:`mslam.system.rotation_start`).

``last_status`` is ``"ok"``, ``"same"`` (i is j), ``"few_inliers"`` or ``"parallax"``;
``last_info`` has the inlier count, the homography parallax (pixels), the median triangulation
angle (degrees) and K's mean focal length (pixels) of the last pair; ``last_R_ji`` (3, 3) the
rotation of a pair flagged ``"parallax"`` (well determined without parallax; the frontend poses such frames by
rotation only), else None.

Memory: ``cache`` (per-frame work, per-pair flows), ``views`` (pointmaps of ``mono``) and
``refs`` (depths of the third view) are bounded by ``desc.cache_bytes`` each.

Public names, in reading order:
    TwoViewPriorConfig, TwoViewPrior
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import numpy as np

from mslam.datasets.frame import Frame
from mslam.priors.base import PairPrediction
from mslam.priors.cache import ByteLRU
from mslam.priors.descriptors import descriptor_Q, patch_descriptors
from mslam.priors.rgbd import FAILED_Q, fill_depth
from mslam.priors.twoview_config import TwoViewPriorConfig
from mslam.priors.twoview_flow import guided_flow, sift_keypoints
from mslam.priors.twoview_geometry import (
    essential_pose,
    flow_consistency,
    focal_guess_intrinsics,
    forward_backward_error,
    refine_pose,
    reprojection_error,
    triangulate_midpoint,
)
from mslam.priors.twoview_homography import homography_fit, homography_rotation
from mslam.priors.twoview_planar import ReferenceDepths, choose_pose, pose_candidates
from mslam.priors.twoview_prefetch import (
    FlowPrefetch,
    desc_key,
    flow_key,
    pair_keys,
    pair_work,
    sift_key,
)
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import backproject, scale_intrinsics

__all__ = ["TwoViewPrior", "TwoViewPriorConfig"]


class TwoViewPrior:
    """MASt3R stand-in for RGB-only frames (module docstring).

    Args:
        K: (3, 3) intrinsics valid at ``image_size`` (calibrated), or None for the focal guess.
        image_size: ``(W, H)`` at which ``K`` is valid (required with ``K``).
        cfg: parameters.
        focal_scale: uncalibrated, the focal length over the guess's.
    """

    #: Pointmaps at a scale of their own, not metres (mslam.system.global_opt.Backend.spread_depths).
    metric: ClassVar[bool] = False

    #: The frontend waits for a pair with enough parallax before fixing the first keyframe.
    needs_parallax = True

    def __init__(
        self,
        K: FloatArray | None = None,
        image_size: tuple[int, int] | None = None,
        cfg: TwoViewPriorConfig = TwoViewPriorConfig(),  # noqa: B008 (frozen, immutable)
        focal_scale: float = 1.0,
    ) -> None:
        if K is not None:
            K = np.asarray(K, dtype=np.float64)
            if K.shape != (3, 3) or image_size is None:
                raise ValueError("K: expected (3, 3) intrinsics together with image_size (W, H)")
        self.K, self.image_size, self.cfg = K, image_size, cfg
        self.focal_scale = float(focal_scale)
        self.last_status = "none"
        self.last_R_ji: FloatArray | None = None
        self.last_info: dict[str, float] = {}
        #: Descriptors, keypoints and flows (recomputed after eviction), bounded in bytes.
        self.cache = ByteLRU(cfg.desc.cache_bytes)
        #: Frame index -> its last two-view pointmap in its own camera and C (``mono``).
        self.views = ByteLRU(cfg.desc.cache_bytes)
        #: The third view: each image's depth from its widest-angle pair (``third_view``).
        self.refs = ReferenceDepths(cfg.desc.cache_bytes)
        self._prefetch = FlowPrefetch(pair_work(cfg), pair_keys)

    def K_for(self, frame: Frame) -> FloatArray:
        """Intrinsics at the frame's resolution (the focal guess when uncalibrated)."""
        H, W = frame.shape
        if self.K is None or self.image_size is None:  # the constructor sets both or neither
            s = self.focal_scale
            return focal_guess_intrinsics(W, H) @ np.diag([s, s, 1.0])
        size = (int(self.image_size[0]), int(self.image_size[1]))
        if (W, H) == size:
            return self.K
        return scale_intrinsics(self.K, size, (W, H))

    def _cached(self, key: tuple, fn):
        """The cached value of ``key``, else the prefetched one, else ``fn()``; stored."""
        return self.cache.get(key, lambda: _or_else(self._prefetch.take(key), fn))

    def _desc(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        D, contrast = self._cached(
            desc_key(frame), lambda: patch_descriptors(frame.rgb, self.cfg.desc)
        )
        return D, descriptor_Q(contrast, self.cfg.q_gain, self.cfg.q_contrast)

    # -- protocol ----------------------------------------------------------------------------
    def mono(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """``X_ii (H, W, 3), C_ii (H, W)``: the last two-view pointmap of this image, else a
        fronto-parallel plane at distance 1 with ``C = 1`` (module docstring)."""
        view = self.views.peek(int(frame.index))
        if view is not None and view[0].shape[:2] == frame.shape:
            return view[0].copy(), view[1].copy()
        return self._plane(frame)

    def _plane(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        H, W = frame.shape
        X = backproject(np.ones((H, W)), self.K_for(frame))
        X /= np.median(np.linalg.norm(X, axis=-1))
        return X, np.ones((H, W))

    def pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        """Both pointmaps in camera i from flow, essential matrix and triangulation.

        Sets ``last_status`` and ``last_info``. Shapes: X (H, W, 3), C/Q (H, W), D (H, W, F).
        """
        if frame_i.shape != frame_j.shape:
            raise ValueError(f"frame_j: size {frame_j.shape} differs from frame_i {frame_i.shape}")
        D_ii, Q_ii = self._desc(frame_i)
        D_jj, Q_jj = self._desc(frame_j)
        if frame_i.index == frame_j.index and np.array_equal(frame_i.rgb, frame_j.rgb):
            X, C = self.mono(frame_i)
            self.last_status, self.last_info = "same", {"inliers": 0, "parallax_px": 0.0}
            return PairPrediction(X, C, D_ii, Q_ii, X.copy(), np.ones_like(C), D_jj, Q_jj)
        geo = self.reconstruct(frame_i, frame_j)
        if geo is None:
            X_ii, C_ii = self._plane(frame_i)
            X_ji, _ = self._plane(frame_j)
            Q_fail = np.full_like(Q_jj, FAILED_Q)
            return PairPrediction(X_ii, C_ii, D_ii, Q_ii, X_ji, np.ones_like(C_ii), D_jj, Q_fail)
        X_ii, C_ii, X_ji, C_ji = geo
        return PairPrediction(X_ii, C_ii, D_ii, Q_ii, X_ji, C_ji, D_jj, Q_jj)

    @property
    def prefetching(self) -> bool:
        """Whether :meth:`prefetch` does anything (``cfg.prefetch``)."""
        return self.cfg.prefetch

    def prefetch(self, frame: Frame, partner: Frame | None = None) -> None:
        """Start the work of ``pair(frame, partner)`` that depends on the two images alone
        (and ``frame``'s descriptors) on a worker thread (:mod:`twoview_prefetch`)."""
        if self.cfg.prefetch:
            self._prefetch.start(frame, partner, self.cache)

    def join_prefetch(self) -> None:
        """Wait for the prefetch in flight, if any (what was not taken is dropped)."""
        self._prefetch.join()

    # -- geometry ----------------------------------------------------------------------------
    def reconstruct(self, frame_i: Frame, frame_j: Frame):
        """``(X_ii, C_ii, X_ji, C_ji)`` in camera i, normalised, or None for a degenerate pair.

        Also remembers each image's pointmap in its own camera for :meth:`mono`.
        """
        cfg = self.cfg
        K = self.K_for(frame_i)
        key = flow_key(frame_i, frame_j)
        F_ij, F_ji, guided = self.cache.get(key, lambda: self._flow(frame_i, frame_j, key))
        self.last_R_ji = None
        z_ref = [self._remembered_depth(f, F_ij.shape[:2]) for f in (frame_i, frame_j)]
        R, t, n_inl, parallax, angle, ambiguous = self._pose_of(key, F_ij, F_ji, K, z_ref)
        self.last_info = {"inliers": n_inl, "parallax_px": parallax, "angle_deg": angle,
                          "focal_px": 0.5 * float(K[0, 0] + K[1, 1]),
                          "guided": float(guided), "ambiguous": float(ambiguous)}  # fmt: skip
        if n_inl < cfg.min_inliers:
            self.last_status = "few_inliers"
            return None
        if parallax < cfg.min_parallax_px:
            self.last_status, self.last_R_ji = "parallax", R
            return None
        X_ii, C_ii, ok_i = self._view(F_ij, F_ji, K, R, t, forward=True)
        X_ji, C_ji, ok_j = self._view(F_ji, F_ij, K, R, t, forward=False)
        dist = np.concatenate([np.linalg.norm(X_ii[ok_i], axis=-1),
                               np.linalg.norm(X_ji[ok_j], axis=-1)])  # fmt: skip
        if min(ok_i.sum(), ok_j.sum()) < cfg.min_inliers or not np.median(dist) > 0:
            self.last_status = "few_inliers"  # too few pixels triangulate in one image
            return None
        s = 1.0 / np.median(dist)
        X_ii, X_ji = X_ii * s, X_ji * s
        if not (np.all(np.isfinite(X_ii)) and np.all(np.isfinite(X_ji))):
            self.last_status = "few_inliers"
            return None
        self.last_status = "ok"
        self._remember(frame_i, X_ii, C_ii, angle)
        self._remember(frame_j, X_ji @ R.T + s * t, C_ji, angle)  # X_jj = R_ji X_ji + s t_ji
        return X_ii, C_ii, X_ji, C_ji

    def _reverse(self, key: tuple):
        """The cached entry of the pair ``key`` in the other direction, or None."""
        return self.cache.peek((key[0], key[2], key[1]))

    def _pose_of(self, flow_key: tuple, F_ij, F_ji, K, z_ref):
        """:meth:`_pose` of the pair, or the inverse of the pose already found for (j, i):
        ``R_ij = R_jiᵀ``, ``t_ij = -R_jiᵀ t_ji`` (so both directions of an edge agree, and the
        backward decode of a graph edge costs no second RANSAC and refinement)."""
        key = ("pose", *flow_key[1:])
        rev = self._reverse(key)
        if rev is not None:
            R, t, n_inl, parallax, angle, ambiguous = rev
            return (R.T, -R.T @ t, n_inl, parallax, angle, ambiguous)
        return self._cached(key, lambda: self._pose(F_ij, F_ji, K, *z_ref))

    def _flow(self, frame_i: Frame, frame_j: Frame, key: tuple | None = None):
        """``F_ij, F_ji, guided`` (:func:`guided_flow`, keypoints cached per image; or
        prefetched, its keypoints looked up as the flow did), or the flows already computed
        for (j, i), swapped. ``key``: the pair's cache key (computed when not given)."""
        key = flow_key(frame_i, frame_j) if key is None else key
        rev = self._reverse(key)
        if rev is not None:
            return rev[1], rev[0], rev[2]
        kp: list[Callable[[], object] | None] = [None, None]
        if self.cfg.guide.enabled:
            kp = [self._keypoints(frame_i), self._keypoints(frame_j)]
        pre = self._prefetch.take(key)
        if pre is not None:
            flows, guide_used = pre
            for get in kp if guide_used else []:
                if get is not None:
                    get()
            return flows
        return guided_flow(frame_i.rgb, frame_j.rgb, kp[0], kp[1], self.cfg.fb_px, self.cfg.guide)

    def _keypoints(self, frame: Frame) -> Callable[[], object]:
        """The frame's SIFT keypoints on demand: computed (once per image) only when a pair
        needs the guide; or prefetched, if the prefetch is done with them."""
        compute = lambda: sift_keypoints(frame.rgb, self.cfg.guide)
        return lambda: self.cache.get(
            sift_key(frame), lambda: _or_else(self._prefetch.take(sift_key(frame), False), compute)
        )

    def _remember(self, frame: Frame, X: FloatArray, C: FloatArray, angle_deg: float) -> None:
        X = X / np.median(np.linalg.norm(X, axis=-1))
        self.views.put(int(frame.index), (X, C))
        self.refs.offer(int(frame.index), X[..., 2], angle_deg)

    def intrinsics_known(self) -> bool:
        """The focal length is the calibration's or the video's own (``focal_scale``)."""
        return self.K is not None or self.focal_scale != 1.0

    def _remembered_depth(self, frame: Frame, shape) -> FloatArray | None:
        """Depth (H, W) of the frame's widest-angle reconstruction (``third_view``), else None;
        only with a known focal length (``TwoViewPriorConfig.third_view``)."""
        if not self.cfg.third_view or not self.intrinsics_known():
            return None
        return self.refs.depth(int(frame.index), shape)

    def _pose(self, F_ij: FloatArray, F_ji: FloatArray, K: FloatArray, z_i=None, z_j=None):
        """RANSAC essential matrix on grid-subsampled consistent flow, refined, and the planar
        ambiguity resolved with remembered depths ``z_i``, ``z_j`` (:mod:`twoview_planar`);
        returns ``R_ji, t_ji, n_inliers, parallax (pixels), median triangulation angle
        (degrees), ambiguous``."""
        e_fb, _ = forward_backward_error(F_ij, F_ji)
        if np.mean(e_fb < self.cfg.fb_px) < self.cfg.min_flow_frac:
            return np.eye(3), np.zeros(3), 0, 0.0, 0.0, False
        good = e_fb < self.cfg.pose_fb_px
        step = max(1, int(np.sqrt(good.sum() / self.cfg.max_ransac_points)))
        sub = np.zeros_like(good)
        sub[step // 2 :: step, step // 2 :: step] = True
        v, u = np.nonzero(good & sub)
        uv_i = np.stack([u, v], -1).astype(np.float64)
        uv_j = uv_i + F_ij[v, u]
        if len(uv_i) < self.cfg.min_inliers:
            return np.eye(3), np.zeros(3), 0, 0.0, 0.0, False
        R, t, inl = essential_pose(uv_i, uv_j, K, self.cfg.ransac_px)
        if inl.sum() < self.cfg.min_inliers:
            return R, t, int(inl.sum()), 0.0, 0.0, False
        ambiguous = False
        if self.cfg.planar_candidates:
            cands = pose_candidates(uv_i[inl], uv_j[inl], K, R, t, self.cfg.ransac_px)
            R, t, ambiguous = choose_pose(cands, uv_i[inl], uv_j[inl], K, z_i, z_j,
                                          self.cfg.ambiguity)  # fmt: skip
            R, t = refine_pose(uv_i[inl], uv_j[inl], K, R, t)  # on all inliers
        else:
            R, t = refine_pose(uv_i[inl], uv_j[inl], K, R, t)
        focal_free = self.K is None and self.cfg.focal_free_parallax
        fit = homography_fit(uv_i, uv_j, K, self.cfg.ransac_px, focal_free=focal_free)
        parallax = fit.parallax_px
        if focal_free and fit.H is not None and parallax < self.cfg.min_parallax_px:
            R = homography_rotation(fit.H, K, fit.focal_px)  # the rotation of some camera
        _, angle, ok = triangulate_midpoint(uv_i[inl], uv_j[inl], K, R, t)
        angle_deg = float(np.degrees(np.median(np.where(ok, angle, 0.0))))
        return R, t, int(inl.sum()), parallax, angle_deg, ambiguous

    def _view(self, F_ab, F_ba, K, R, t, forward: bool):
        """Triangulate every pixel of image a (i when ``forward``, else j) with flow ``F_ab``;
        returns its pointmap in camera i (H, W, 3), confidence (H, W) and validity (H, W)."""
        cfg = self.cfg
        H, W = F_ab.shape[:2]
        e_fb, inside, F_sym = flow_consistency(F_ab, F_ba)
        u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        uv_a = np.stack([u, v], -1)
        uv_b = uv_a + F_sym  # both views: one correspondence per point
        uv_i, uv_j = (uv_a, uv_b) if forward else (uv_b, uv_a)
        X_i, angle, ok = triangulate_midpoint(uv_i, uv_j, K, R, t)
        r = reprojection_error(X_i, uv_i, uv_j, K, R, t)
        ok &= inside & (e_fb < cfg.fb_px) & (r < cfg.max_reproj_px)
        w_ang = 1.0 - np.exp(-((np.degrees(angle) / cfg.angle_sigma_deg) ** 2))
        w_r = np.exp(-((np.where(ok, r, 0.0) / cfg.reproj_sigma) ** 2))
        w_fb = np.exp(-((np.where(ok, e_fb, 0.0) / cfg.fb_sigma) ** 2))
        C = np.where(ok, 1.0 + cfg.conf_max * w_ang * w_r * w_fb, 1.0)
        X_a = X_i if forward else X_i @ R.T + t  # in camera a
        z, _ = fill_depth(np.where(ok, X_a[..., 2], 0.0), default=1.0)
        X_a = backproject(z, K)
        X_i_out = X_a if forward else (X_a - t) @ R  # X_i = R_jiᵀ (X_j - t_ji)
        return X_i_out, C, ok


def _or_else(value, fn):
    """``value`` unless it is None, else ``fn()``."""
    return fn() if value is None else value
