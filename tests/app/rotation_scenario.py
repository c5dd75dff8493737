"""The pure-rotation run the rotation tests share (the ``rotation_run`` fixture of conftest.py).

:func:`run_rotation` runs ``synthetic:rotation:60`` at 96x72 (226° turned about the camera
centre, uncalibrated: the two-view prior's 60° focal guess for a 70° camera) with the fast
kernels, and tracking is given up by force after each frame of ``ROTATION_LOSS_AFTER``
(``SlamSystem.lose_tracking``), so the run always goes through two relocalisations against
the keyframes made under rotation, whether or not tracking would have failed by itself there.
The first loss comes early (few keyframes; the relocalised frame has never been paired, so
the two-view prior has no depth for it), the second once the map holds keyframes posed by
rotation alone; between them, frame 40 is 34° from its keyframe (frame 32), a pair where
plain optical flow locks onto a wrong motion (``mslam.priors.twoview_flow``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mslam.system import SlamSystem
from mslam.system.state import FrameStatus

ROTATION = "synthetic:rotation:60:96x72"
#: the frames after which tracking is given up (after frame 39 the view has turned ~150° and
#: the map holds keyframes posed by rotation alone)
ROTATION_LOSS_AFTER = (20, 39)


@dataclass(frozen=True)
class RotationRun:
    """The rotation run and its orientations against the truth.

    Attributes:
        system: the ``SlamSystem`` after the run.
        idx: (N,) indices of the posed frames.
        err_deg: (N,) orientation error of each posed frame relative to the first posed frame,
            estimate against truth, degrees.
        status: frame index -> ``FrameStatus``.
        turned_deg: the angle the true camera turns over the sequence (sum of the steps).
    """

    system: SlamSystem
    idx: np.ndarray
    err_deg: np.ndarray
    status: dict[int, FrameStatus]
    turned_deg: float


class _LoseTracking:
    """Frame observer that gives tracking up after each frame of ``after``."""

    def __init__(self, after: tuple[int, ...]) -> None:
        self.after = after

    def after_frame(self, i: int, frame: object, system: SlamSystem, status: FrameStatus) -> None:
        if i in self.after:
            system.lose_tracking()


def angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of ``R_a^T R_b`` for (N, 3, 3) stacks, degrees (N,)."""
    cos = (np.einsum("nij,nij->n", R_a, R_b) - 1) / 2  # trace(R_a^T R_b)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def orientation_errors_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """(N,) error of each orientation relative to the first, estimate (N, 3, 3) against
    truth (N, 3, 3), degrees."""
    rel_est = np.einsum("ji,njk->nik", R_est[0], R_est)
    rel_gt = np.einsum("ji,njk->nik", R_gt[0], R_gt)
    return angle_deg(rel_est, rel_gt)


def run_rotation() -> RotationRun:
    """Run the scenario of the module docstring and measure its orientations."""
    import mslam_fast
    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.system import open_source, run_slam
    from mslam_ref import so3

    mslam_fast.init("cpu", "f64")
    cfg = load_config("twoview")
    src = open_source(ROTATION, cfg, prior="twoview")
    observer = _LoseTracking(ROTATION_LOSS_AFTER)
    system, _ = run_slam(src, cfg, load_kernels("fast"), observer=observer)
    idx, _, T = system.frame_poses()
    R_true = so3.to_matrix(np.asarray(src.sequence.T_WC)[:, 3:7])
    return RotationRun(
        system=system,
        idx=idx,
        err_deg=orientation_errors_deg(so3.to_matrix(T[:, 3:7]), R_true[idx]),
        status={p.index: p.status for p in system.poses},
        turned_deg=float(angle_deg(R_true[:-1], R_true[1:]).sum()),
    )
