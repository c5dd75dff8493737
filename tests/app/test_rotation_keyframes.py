"""A pure rotation with the two-view prior: frames are posed, keyframes follow the angle.

Under a pure rotation the two-view prior's pairs have no parallax (their triangulation angle is
a small fraction of a degree), so their depths are noise. The frontend poses such frames by
rotation alone and makes a keyframe only when the overlap with the last keyframe is lost
(``mslam.system.parallax``): the keyframes follow the angle turned, not the frame count.
"""

from __future__ import annotations

import numpy as np
import pytest

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.state import FrameStatus
from mslam_ref import sim3

ROTATION = "synthetic:rotation:60:96x72"
DEG_PER_KEYFRAME = 15.0  # at most one keyframe per this many degrees turned (70° view)
MIN_POSED = 0.9  # share of frames with a pose


@pytest.fixture(scope="module")
def rotation_run():
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    cfg = load_config("twoview")
    src = open_source(ROTATION, cfg, prior="twoview")
    system, _ = run_slam(src, cfg, load_kernels("fast"))
    R = sim3.to_matrix(np.asarray(src.sequence.T_WC))[:, :3, :3]
    cos = (np.einsum("nij,nij->n", R[:-1], R[1:]) - 1) / 2  # trace(R_a^T R_b) per step
    turned = float(np.degrees(np.arccos(np.clip(cos, -1, 1))).sum())
    return system, turned


def test_pure_rotation_makes_keyframes_by_angle_not_by_frame(rotation_run) -> None:
    system, turned = rotation_run
    assert len(system.keyframes) <= turned / DEG_PER_KEYFRAME, (len(system.keyframes), turned)
    assert any(p.status == FrameStatus.ROTATION for p in system.poses)


def test_pure_rotation_frames_keep_their_poses(rotation_run) -> None:
    system, _ = rotation_run
    idx, _, T = system.frame_poses()
    assert len(idx) >= MIN_POSED * system.stats.frames
    assert np.all(np.isfinite(T))
