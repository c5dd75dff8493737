"""Synthetic scenes — procedural textured rooms, named camera paths, exact ray casting.

The built-in ground truth of the project: a closed room with textured walls, floor and
ceiling, boxes and spheres (texture, occlusions, depth edges), rendered by exact ray casting
in vectorised NumPy at any resolution, and named camera paths (``loop``, ``jump``,
``detour``, ``rotation``, ``forward``) as camera-to-world Sim(3) poses. The application turns
these into frame sequences (``mslam.datasets.synthetic.make_sequence``) and noisy MASt3R-like
pointmaps (``mslam.priors.synthetic``).

Public names, in reading order:
    MAX_FRAMES, MAX_PIXELS, check_synthetic_size, intrinsics, PATHS, camera_path, jump_indices,
    detour_indices, Scene, make_scene, cast_rays, render
"""

from __future__ import annotations

from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import intrinsics_from_fov
from mslam_ref.synthetic.paths import PATHS, camera_path, detour_indices, jump_indices
from mslam_ref.synthetic.scene import Scene, cast_rays, make_scene, render

__all__ = [
    "MAX_FRAMES",
    "MAX_PIXELS",
    "PATHS",
    "Scene",
    "camera_path",
    "cast_rays",
    "check_synthetic_size",
    "detour_indices",
    "intrinsics",
    "jump_indices",
    "make_scene",
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
    return intrinsics_from_fov(width, height, fov_deg)
