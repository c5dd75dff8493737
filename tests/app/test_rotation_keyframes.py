"""A pure rotation with the two-view prior: frames are posed, keyframes follow the angle.

Under a pure rotation the two-view prior's pairs have no parallax (their triangulation angle is
a small fraction of a degree), so their depths are noise. The frontend poses such frames by
rotation alone and makes a keyframe only when the overlap with the last keyframe is lost
(``mslam.system.parallax``): the keyframes follow the angle turned, not the frame count. The run
is the shared ``rotation_run`` (tests/app/rotation_scenario.py).
"""

from __future__ import annotations

import numpy as np
from rotation_scenario import RotationRun

from mslam.system.state import FrameStatus

DEG_PER_KEYFRAME = 15.0  # at most one keyframe per this many degrees turned (70° view)
MIN_POSED = 0.9  # share of frames with a pose


def test_pure_rotation_makes_keyframes_by_angle_not_by_frame(rotation_run: RotationRun) -> None:
    system, turned = rotation_run.system, rotation_run.turned_deg
    assert len(system.keyframes) <= turned / DEG_PER_KEYFRAME, (len(system.keyframes), turned)
    assert any(p.status == FrameStatus.ROTATION for p in system.poses)


def test_pure_rotation_frames_keep_their_poses(rotation_run: RotationRun) -> None:
    system = rotation_run.system
    idx, _, T = system.frame_poses()
    assert len(idx) >= MIN_POSED * system.stats.frames
    assert np.all(np.isfinite(T))
