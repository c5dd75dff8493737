"""A pure rotation with the two-view prior through a relocalisation: orientations stay close.

The shared ``rotation_run`` (tests/app/rotation_scenario.py: ``synthetic:rotation:60`` at 96x72,
uncalibrated) gives tracking up by force once the view has turned ~150°, so the next frames
are relocalised against keyframes made under rotation. Those keyframes were posed by rotation
alone; their pointmaps are their keyframe's points seen through their own rays
(``mslam.system.parallax.rotated_pointmap``), so a relocalised frame and the frames after it are
placed by real geometry rather than by a pair's noise depths. The properties hold whether or
not tracking would have been lost by itself.
"""

from __future__ import annotations

from rotation_scenario import ROTATION_LOSS_AFTER, RotationRun
from tolerances import ROTATION_ONLY_ORIENTATION_DEG

from mslam.system.state import FrameStatus

MIN_POSED = 0.9  # share of frames with a pose
RELOC_WITHIN = 3  # frames after the loss by which the map has taken the camera back


def test_the_camera_is_relocalised_soon_after_tracking_is_lost(rotation_run: RotationRun) -> None:
    reloc = [i for i, s in rotation_run.status.items() if s == FrameStatus.RELOCALISED]
    assert any(ROTATION_LOSS_AFTER < i <= ROTATION_LOSS_AFTER + RELOC_WITHIN for i in reloc), reloc


def test_every_relocalised_frame_lands_at_its_true_orientation(rotation_run: RotationRun) -> None:
    run = rotation_run
    reloc = [n for n, i in enumerate(run.idx) if run.status[int(i)] == FrameStatus.RELOCALISED]
    assert reloc
    assert run.err_deg[reloc].max() < ROTATION_ONLY_ORIENTATION_DEG, run.err_deg[reloc].round(1)


def test_every_frame_is_posed_close_to_its_true_orientation(rotation_run: RotationRun) -> None:
    run = rotation_run
    assert len(run.idx) >= MIN_POSED * run.system.stats.frames
    assert run.err_deg.max() < ROTATION_ONLY_ORIENTATION_DEG, run.err_deg.round(1)
