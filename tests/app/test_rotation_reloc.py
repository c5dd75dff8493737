"""A pure rotation with the two-view prior through relocalisations: orientations stay close.

The shared ``rotation_run`` (tests/app/rotation_scenario.py: ``synthetic:rotation:60`` at 96x72,
uncalibrated) gives tracking up by force twice: early, and once the view has turned ~150°, so
frames are relocalised against keyframes made under rotation. Those keyframes were posed by
rotation alone; their pointmaps are their keyframe's points seen through their own rays
(``mslam.system.parallax.rotated_pointmap``). A relocalised keyframe takes its depth and pose
from its pair with the accepted candidate (``ParallaxSteps.place_relocalised``): the two-view
prior has no depth for a frame it has never paired, and a keyframe without depth cannot be
moved by the backend. So a relocalised frame and the frames after it are placed by real
geometry. The properties hold whether or not tracking would have been lost by itself, and a
wrong orientation would not pass unreported (the final trajectory's orientation-jump test).
"""

from __future__ import annotations

from rotation_scenario import ROTATION_LOSS_AFTER, RotationRun
from tolerances import ROTATION_ONLY_ORIENTATION_DEG

from mslam.system.divergence import trajectory_warnings
from mslam.system.state import FrameStatus

MIN_POSED = 0.9  # share of frames with a pose
RELOC_WITHIN = 3  # frames after the loss by which the map has taken the camera back


def test_the_camera_is_relocalised_soon_after_tracking_is_lost(rotation_run: RotationRun) -> None:
    reloc = [i for i, s in rotation_run.status.items() if s == FrameStatus.RELOCALISED]
    for lost in ROTATION_LOSS_AFTER:
        assert any(lost < i <= lost + RELOC_WITHIN for i in reloc), (lost, reloc)


def test_every_relocalised_frame_lands_at_its_true_orientation(rotation_run: RotationRun) -> None:
    run = rotation_run
    reloc = [n for n, i in enumerate(run.idx) if run.status[int(i)] == FrameStatus.RELOCALISED]
    assert reloc
    assert run.err_deg[reloc].max() < ROTATION_ONLY_ORIENTATION_DEG, run.err_deg[reloc].round(1)


def test_every_frame_is_posed_close_to_its_true_orientation(rotation_run: RotationRun) -> None:
    run = rotation_run
    assert len(run.idx) >= MIN_POSED * run.system.stats.frames
    assert run.err_deg.max() < ROTATION_ONLY_ORIENTATION_DEG, run.err_deg.round(1)


def test_the_final_trajectory_has_no_orientation_jump(rotation_run: RotationRun) -> None:
    """The health watch's test (``mslam.system.turns``) finds nothing to report on this run;
    tests/app/test_divergence.py shows it reports a keyframe 40° off."""
    run = rotation_run
    idx, _, T = run.system.frame_poses()
    assert trajectory_warnings(T, idx=idx) == []
