"""The RGB-D prior's parameters (``mslam.priors.rgbd``; the run config's ``rgbd_prior.*``).

Public names: RGBDPriorConfig.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mslam.priors.descriptors import DescriptorConfig

__all__ = ["RGBDPriorConfig"]


@dataclass(frozen=True)
class RGBDPriorConfig:
    """Parameters of the RGB-D prior.

    Attributes:
        features: "sift" or "orb".
        n_features: keypoints per image (the strongest responses are kept).
        contrast_threshold: SIFT's DoG contrast threshold. OpenCV's default (0.04) is absolute
            in intensity and starves low-contrast images (160x120 frames of smooth textures
            kept 12-140 of the 2000 keypoints); a low threshold lets ``n_features`` rank by
            response instead, so the detector yields its quota whatever the contrast.
        ratio: Lowe ratio-test threshold.
        detect_min_width: frames narrower than this are upscaled for detection only.
        detect_max_width: frames wider than this are downscaled to it for detection only
            (0 = never): keypoints at 512 px cost 4x those at 256 px, and ICP on the depth
            maps makes up the lost keypoint precision.
        ransac_px: RANSAC reprojection threshold in frame pixels.
        ransac_iters: RANSAC iterations.
        min_inliers: fewer inliers means "pose failed".
        max_translation: a PnP translation longer than this (m) is rejected as degenerate.
        icp_iters: point-to-plane ICP iterations refining the PnP pose on the depth maps
            (0 = off).
        icp_points: about this many of j's pixels take part (a regular grid,
            ``rgbd_pose.icp_sample``), whatever the resolution.
        icp_dist, icp_dist_final: association distance (m) of the first and last ICP iteration
            (geometric schedule in between).
        icp_min_frac: the refined pose is kept only if at least this share of j's valid pixels
            is associated at the end.
        icp_max_change: ... and if it moves the PnP pose by less than this (m, and rad).
        icp_min_agree: ... and if it still explains this share of the matches the PnP pose
            explains (ICP can slide along a plane; ``rgbd_pose.icp_agrees``).
        fill_depth: depth (m) used when a frame has no valid depth at all.
        conf_max, conf_sigma: ``C = 1 + conf_max exp(-σ(z) / conf_sigma)`` on valid depth.
        consistency_tol: relative depth disagreement that marks a pixel of j inconsistent.
        inconsistent_factor, covis_factor: multipliers of ``C - 1`` (inconsistent / out of view).
        q_gain, q_contrast: ``Q = 1 + q_gain tanh(contrast / q_contrast)``.
        desc: patch-descriptor parameters.
        prefetch: :meth:`RGBDPrior.prefetch` computes a frame's own work (keypoints,
            descriptors, depth view, ICP target) on a worker thread while the frame before it
            is tracked (``mslam.system.run``); off by default (docs/system.md, "speed").
    """

    features: str = "sift"
    n_features: int = 2000
    contrast_threshold: float = 0.01
    ratio: float = 0.8
    detect_min_width: int = 480
    detect_max_width: int = 0
    ransac_px: float = 1.5
    ransac_iters: int = 500
    min_inliers: int = 15
    max_translation: float = 5.0
    icp_iters: int = 12
    icp_points: int = 10000
    icp_dist: float = 0.1
    icp_dist_final: float = 0.02
    icp_min_frac: float = 0.25
    icp_max_change: float = 0.15
    icp_min_agree: float = 0.5
    fill_depth: float = 3.0
    conf_max: float = 20.0
    conf_sigma: float = 0.05
    consistency_tol: float = 0.05
    inconsistent_factor: float = 0.1
    covis_factor: float = 0.2
    q_gain: float = 6.0
    q_contrast: float = 0.04
    desc: DescriptorConfig = field(default_factory=DescriptorConfig)
    prefetch: bool = False

    def __post_init__(self) -> None:
        if self.features not in ("sift", "orb"):
            raise ValueError(f"features: expected 'sift' or 'orb', got {self.features!r}")
        if self.fill_depth <= 0 or self.ransac_px <= 0 or self.min_inliers < 4:
            raise ValueError("fill_depth, ransac_px must be > 0 and min_inliers >= 4")
