"""A pure rotation with the two-view prior through a relocalisation: orientations stay close.

On ``synthetic:rotation:60`` at 128x96 (226° turned, uncalibrated: the prior's 60° focal
guess for a 70° camera) tracking is lost once the view has turned past the keyframes made under
rotation, and the frame is relocalised against one of them. Those keyframes were posed by
rotation alone; their pointmaps are their keyframe's points seen through their own rays
(``mslam.system.parallax.rotated_pointmap``), so the relocalised frame and the frames after it
are placed by real geometry rather than by a pair's noise depths.
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import ROTATION_ONLY_ORIENTATION_DEG

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.state import FrameStatus
from mslam_ref import so3

ROTATION = "synthetic:rotation:60:128x96"
MIN_POSED = 0.9  # share of frames with a pose


@pytest.fixture(scope="module")
def rotation_errors():
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    cfg = load_config("twoview")
    src = open_source(ROTATION, cfg, prior="twoview")
    system, _ = run_slam(src, cfg, load_kernels("fast"))
    idx, _, T = system.frame_poses()
    R_est = so3.to_matrix(T[:, 3:7])
    R_gt = so3.to_matrix(np.asarray(src.sequence.T_WC)[idx, 3:7])
    # Orientation relative to the first posed frame, estimate against truth.
    rel_est = np.einsum("ji,njk->nik", R_est[0], R_est)
    rel_gt = np.einsum("ji,njk->nik", R_gt[0], R_gt)
    cos = (np.einsum("nij,nij->n", rel_est, rel_gt) - 1) / 2
    err = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    status = {p.index: p.status for p in system.poses}
    return system, idx, err, status


@pytest.mark.xfail(
    strict=True,
    reason="this scenario does not lose tracking with the two-view prior's symmetric flow (all 60 "
    "frames tracked, orientation error at most 9.8 degrees, 2026-11-26), so nothing is "
    "relocalised; a scenario that relocalises after rotation-only keyframes is wanted",
)
def test_frames_after_relocalisation_keep_their_orientation(rotation_errors) -> None:
    _, idx, err, status = rotation_errors
    reloc = [int(i) for i in idx if status.get(int(i)) == FrameStatus.RELOCALISED]
    assert reloc, "the scenario relocalises once tracking is lost (measured 2026-11-26: frame 40)"
    after = idx >= reloc[0]
    assert err[after].max() < ROTATION_ONLY_ORIENTATION_DEG, err[after].round(1)


def test_every_frame_is_posed_close_to_its_true_orientation(rotation_errors) -> None:
    system, idx, err, _ = rotation_errors
    assert len(idx) >= MIN_POSED * system.stats.frames
    assert err.max() < ROTATION_ONLY_ORIENTATION_DEG, err.round(1)
