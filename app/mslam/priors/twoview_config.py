"""Parameters of the two-view prior (:mod:`mslam.priors.twoview`, docs/priors.md): the
``twoview_prior`` section of a configuration.

Public names: TwoViewPriorConfig
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mslam.priors.descriptors import DescriptorConfig
from mslam.priors.twoview_flow import GuideConfig

__all__ = ["TwoViewPriorConfig"]


@dataclass(frozen=True)
class TwoViewPriorConfig:
    """Parameters of the two-view prior (:mod:`mslam.priors.twoview`).

    Attributes:
        fb_px: forward–backward error (pixels) above which a correspondence is not used.
        pose_fb_px: stricter forward–backward limit for the correspondences of the pose.
        max_ransac_points: correspondences (grid subsample) given to the essential matrix.
        ransac_px: RANSAC epipolar threshold (pixels).
        min_inliers: fewer RANSAC inliers means a degenerate pair.
        min_flow_frac: a pair whose share of pixels passing the forward–backward check (fb_px)
            is lower is degenerate too (DIS breaks down under large motion and still returns
            a few hundred self-consistent vectors).
        min_parallax_px: homography parallax (pixels) below which a pair is degenerate. On
            the 7-Scenes kitchen clip (2026-11-26) the translation direction of pairs with
            0.5-1 px was off by a median 39° (16° at 1-1.5 px): flow noise, not geometry.
        max_reproj_px: triangulated pixels reprojecting worse than this are not used.
        conf_max: ``C - 1`` of a perfect pixel.
        angle_sigma_deg, reproj_sigma, fb_sigma: scales of ``w_θ`` (degrees), ``w_r``, ``w_fb``
            (pixels).
        q_gain, q_contrast: ``Q = 1 + q_gain tanh(contrast / q_contrast)``.
        desc: patch-descriptor parameters.
        planar_candidates: also try the homography decompositions as pose hypotheses
            (:mod:`mslam.priors.twoview_planar`).
        third_view: resolve hypotheses the pair cannot tell apart with image i's and j's
            depths from their widest-angle earlier pairs; only with a known focal length (with
            the guess, two pairs' depths are different projective distortions: synthetic loop,
            70° lens, guess 60°: ATE 2.1 % of the path without, 3.4 % with it).
        ambiguity: cost ratio under which hypotheses count as indistinguishable.
        focal_free_parallax: uncalibrated, a pair whose flow is a rotation for *some* focal
            length has no parallax, and its rotation is the homography's at that focal length
            (:mod:`mslam.priors.twoview_homography`).
        self_calibrate: uncalibrated, a run first estimates the focal length and the lens
            from the video where determined: from many views (``camera_from_views``,
            :mod:`mslam.priors.twoview_selfcal`), else from pairs (:mod:`twoview_focal`).
        guide: sparse-feature seeding of the flow for pairs beyond DIS's range
            (:mod:`mslam.priors.twoview_flow`).
        prefetch: :meth:`TwoViewPrior.prefetch` computes the next frame's flow to its
            keyframe on a worker thread (:mod:`mslam.priors.twoview_prefetch`).
    """

    fb_px: float = 1.0
    pose_fb_px: float = 0.3
    max_ransac_points: int = 2000
    ransac_px: float = 1.0
    min_inliers: int = 200
    min_flow_frac: float = 0.3
    min_parallax_px: float = 1.0
    max_reproj_px: float = 2.0
    conf_max: float = 20.0
    angle_sigma_deg: float = 3.0
    reproj_sigma: float = 1.0
    fb_sigma: float = 0.5
    q_gain: float = 6.0
    q_contrast: float = 0.04
    desc: DescriptorConfig = field(default_factory=DescriptorConfig)
    guide: GuideConfig = field(default_factory=GuideConfig)
    planar_candidates: bool = True
    third_view: bool = True
    ambiguity: float = 1.5
    focal_free_parallax: bool = True
    self_calibrate: bool = True
    camera_from_views: bool = True
    prefetch: bool = True

    def __post_init__(self) -> None:
        positive = ("fb_px", "pose_fb_px", "ransac_px", "max_reproj_px", "angle_sigma_deg",
                    "reproj_sigma", "fb_sigma", "q_contrast")  # fmt: skip
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        if self.min_inliers < 5 or self.max_ransac_points < self.min_inliers:
            raise ValueError("min_inliers: must be >= 5 and <= max_ransac_points")
        if self.min_parallax_px < 0 or self.conf_max < 0:
            raise ValueError("min_parallax_px, conf_max: must be >= 0")
