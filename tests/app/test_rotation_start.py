"""A video that starts with the camera turning in place (a pan), RGB only, uncalibrated.

The two-view prior has no depth without parallax, so the frontend waits for a pair with
parallax before it fixes keyframe 0. Under a pan that pair never comes before the first view
is out of sight: the map starts without depth from the waiting frames' rotations
(``mslam.system.rotation_start``), and the first keyframe tracked with parallax gets depth.

* ``pan then walk``: the camera turns in place, then walks sideways: every frame is posed,
  the pan's frames at their true orientations and at one centre, and the keyframe the walk
  is tracked against gets depth (tracking never aligns a frame to a plane).
* ``short pan``: a pan that ends before the first view is out of sight is posed at the end of
  the sequence instead of being lost.
* frames that never start a map (a view, then a covered lens) are counted lost at the end, so
  every frame is posed, lost or skipped.
"""

from __future__ import annotations

import numpy as np
import pytest
from rotation_scenario import orientation_errors_deg
from tolerances import PAN_WALK_DIRECTION_DEG, ROTATION_ONLY_ORIENTATION_DEG

from mslam.datasets.frame import Frame
from mslam.system.rotation_start import depthless
from mslam.system.state import FrameStatus
from mslam_ref import so3
from mslam_ref.synthetic import intrinsics, make_scene, render
from mslam_ref.synthetic.paths import look_at

W, H, FOV = 96, 72, 70.0
CENTRE = np.array([0.3, -0.2, 1.4])
PAN_DEG = 2.0  # per frame
N_PAN, N_WALK = 36, 24
WALK_M = 0.02  # per frame, sideways (camera x)


def _frames(n_pan: int, n_walk: int) -> tuple[list[Frame], np.ndarray]:
    """The pan, then a sideways walk at the pan's last orientation; frames and true T_WC."""
    yaw = np.radians(PAN_DEG) * np.arange(n_pan + n_walk).clip(max=n_pan - 1)
    T = look_at(np.broadcast_to(CENTRE, (len(yaw), 3)), yaw, -0.1)
    R_last = so3.to_matrix(T[n_pan - 1, 3:7])
    walk = np.arange(len(yaw)) - (n_pan - 1)
    T[:, :3] += np.outer(walk.clip(min=0) * WALK_M, R_last[:, 0])
    K, scene = intrinsics(W, H, FOV), make_scene(2)
    frames = [
        Frame(i, i / 30.0, render(scene, T[i], K, W, H)[0], None, T[i]) for i in range(len(T))
    ]
    return frames, T


def _run(frames: list[Frame]):
    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.priors.twoview import TwoViewPrior
    from mslam.system.frontend import SlamSystem

    system = SlamSystem(TwoViewPrior(), load_config("twoview"), load_kernels("ref"))
    statuses = [system.process(f) for f in frames]
    system.close()
    return system, statuses


@pytest.fixture(scope="module")
def pan_then_walk():
    frames, T = _frames(N_PAN, N_WALK)
    system, statuses = _run(frames)
    return system, statuses, T


def test_a_pan_at_the_start_is_posed_by_rotation(pan_then_walk) -> None:
    system, statuses, T = pan_then_walk
    idx, _, T_est = system.frame_poses()
    assert len(idx) == len(T)  # every frame posed, none lost
    assert FrameStatus.ROTATION in statuses[:N_PAN]
    pan = idx < N_PAN
    err = orientation_errors_deg(so3.to_matrix(T_est[pan, 3:7]), so3.to_matrix(T[idx[pan], 3:7]))
    assert err.max() < ROTATION_ONLY_ORIENTATION_DEG, err.round(1)
    # ... about one centre: the pan's frames are posed where keyframe 0 is, exactly (a
    # rotation about it, and nothing moves a keyframe without depth).
    assert np.array_equal(
        T_est[pan, :3], np.broadcast_to(system.keyframes[0].T_WC[:3], (pan.sum(), 3))
    )


def test_the_walk_gives_the_map_depth(pan_then_walk) -> None:
    system, _, _ = pan_then_walk
    assert depthless(system.keyframes[0])  # made under the pan
    assert not depthless(system.keyframes.last())  # the keyframe the walk is tracked against
    walk = [p for p in system.poses if p.index >= N_PAN + N_WALK // 2]  # parallax by then
    assert {p.status for p in walk} <= {FrameStatus.TRACKED, FrameStatus.KEYFRAME}
    # The walk leaves the pan's centre sideways, along the last pan frame's x axis.
    _, _, T_est = system.frame_poses()  # every frame, in order (the test above)
    d = so3.to_matrix(T_est[N_PAN - 1, 3:7]).T @ (T_est[-1, :3] - T_est[0, :3])
    assert np.degrees(np.arccos(d[0] / np.linalg.norm(d))) < PAN_WALK_DIRECTION_DEG, d


def test_a_short_pan_is_posed_at_the_end_of_the_sequence() -> None:
    frames, T = _frames(8, 0)
    system, statuses = _run(frames)
    assert statuses[1:] == [FrameStatus.WAITING] * (len(frames) - 1)  # no parallax, no loss
    idx, _, T_est = system.frame_poses()
    assert idx.tolist() == list(range(len(frames)))
    err = orientation_errors_deg(so3.to_matrix(T_est[:, 3:7]), so3.to_matrix(T[:, 3:7]))
    assert err.max() < ROTATION_ONLY_ORIENTATION_DEG, err.round(1)


def test_frames_that_never_start_a_map_are_counted_lost() -> None:
    frames, T = _frames(1, 0)
    grey = np.full_like(frames[0].rgb, 128)  # a covered lens: no pair, no rotation
    frames += [Frame(i, i / 30.0, grey, None, T[0]) for i in (1, 2)]
    system, statuses = _run(frames)
    assert statuses == [FrameStatus.WAITING] * 3 and len(system.keyframes) == 0
    assert [(p.index, p.status) for p in system.poses] == [(i, FrameStatus.LOST) for i in range(3)]
    assert system.stats.lost_frames == 3


def test_the_console_and_summary_count_the_frames_posed_by_rotation(tmp_path, capsys) -> None:
    """A short pan through ``mslam run``: every frame posed, all but keyframe 0 by rotation
    alone, and the console says so."""
    import json

    from mslam.cli import main

    out = tmp_path / "out"
    assert main(["run", "synthetic:rotation:8:64x48", "--prior", "twoview", "--kernels", "ref",
                 "--out", str(out)]) == 0  # fmt: skip
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_with_pose"] == s["frames"] == 8
    assert s["frames_posed_by_rotation"] == 8 - s["keyframes"]
    assert (
        f"{s['frames_posed_by_rotation']} frames posed by rotation alone" in capsys.readouterr().err
    )
