"""A frame without parallax to the last keyframe is recorded at that keyframe's centre.

When the two-view prior finds no parallax between a frame and the last keyframe, the frame is
tracked against the keyframe before it, but its recorded pose is the last keyframe's centre with
the tracked orientation (``SlamSystem.record_near_keyframe``): the frame follows the last
keyframe wherever the backend moves it.
"""

from __future__ import annotations

import numpy as np
from tolerances import F64_SERIES

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.state import FrameStatus
from mslam_ref import sim3, so3

TINY = "synthetic:loop:10:48x36"  # small enough for the NumPy kernels


def test_a_frame_near_the_last_keyframe_takes_its_centre_and_keeps_its_orientation() -> None:
    cfg = load_config(None, [])
    src = open_source(TINY, cfg)
    system, _ = run_slam(src, cfg, load_kernels("ref"))
    last = len(system.keyframes) - 1
    assert last >= 1
    T_kf = system.keyframes[last].T_WC
    # a tracked pose 4 cm and 10° from the last keyframe, as a tracking against an older one gives
    step = np.concatenate([[0.04, -0.01, 0.0], so3.exp(np.radians([0.0, 10.0, 0.0])), [1.0]])
    T_WC = sim3.mul(T_kf, step)
    frame = src.sequence[len(src.sequence) - 1]
    n = len(system.poses)

    status = system.record_near_keyframe(frame, T_WC)

    assert status == FrameStatus.ROTATION and len(system.poses) == n + 1
    rec = system.poses[-1]
    assert rec.kf == last and rec.status == FrameStatus.ROTATION
    T_rec = sim3.mul(T_kf, rec.T_CkCf)
    # the keyframe's centre, the tracked orientation
    np.testing.assert_allclose(T_rec[:3], T_kf[:3], atol=F64_SERIES)
    R_rec, R_trk = so3.to_matrix(T_rec[3:7]), so3.to_matrix(T_WC[3:7])
    np.testing.assert_allclose(R_rec, R_trk, atol=F64_SERIES)
    # and it follows the keyframe when the backend moves it
    system.keyframes[last].T_WC = sim3.mul(sim3.exp(np.r_[0.1, 0, 0, 0, 0.2, 0, 0]), T_kf)
    _, _, T = system.frame_poses()
    np.testing.assert_allclose(T[-1][:3], system.keyframes[last].T_WC[:3], atol=F64_SERIES)
