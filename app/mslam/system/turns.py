"""Orientation jumps — the final trajectory's test for frames that turn too far in one step.

The translation tests of :mod:`mslam.system.divergence` cannot see a wrong orientation under a
pure rotation: the camera centre barely moves, and a step shorter than a share of the Sim(3)
scale is never a jump. A keyframe posed tens of degrees off (a wrong two-view decode) leaves
its trace in the final trajectory all the same: the frames tracked against it and those
tracked against its neighbours disagree, so the orientation steps back and forth between
consecutive frames by about the keyframe's error.

:func:`turn_warnings` takes the posed frames in frame order and flags a turn between two
consecutive frames (frame indices one apart) that exceeds both ``rot_jump_factor`` times the
median of those turns and ``min_rot_jump_deg`` (a camera at rest has a median near zero; a
fast hand-held pan at 30 frames per second turns a few degrees per frame). Frames on either
side of a span without poses are not compared: the camera may have turned while it was lost
(a kidnapped camera, relocalised elsewhere). The test is a report (``summary.json``'s ``warnings``, ``plausible`` false), not a
refusal while running: a frame that turns far from the one before it may be the right one of
the two.

Public names, in reading order:
    TurnConfig, turn_angles_deg, turn_warnings
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mslam_ref import so3
from mslam_ref.conventions import FloatArray

__all__ = ["TurnConfig", "turn_angles_deg", "turn_warnings"]


@dataclass(frozen=True)
class TurnConfig:
    """Thresholds of an orientation jump (module docstring).

    Attributes:
        rot_jump_factor: a turn between consecutive frames larger than this many times the
            median such turn ...
        min_rot_jump_deg: ... and larger than this many degrees is a jump.
        min_frames: pairs of consecutive posed frames needed before the test applies.

    ``synthetic:rotation:60`` turns 3.8° per frame (226° in 60 frames); a keyframe 41° off
    there gave steps of 35-40° between consecutive frames (2026-11-26).
    """

    rot_jump_factor: float = 5.0
    min_rot_jump_deg: float = 15.0
    min_frames: int = 4


def turn_angles_deg(q_a: FloatArray, q_b: FloatArray) -> FloatArray:
    """Angle of the rotation between unit quaternions ``q_a`` and ``q_b`` (..., 4), degrees."""
    R_a = so3.to_matrix(np.asarray(q_a, np.float64))
    R_b = so3.to_matrix(np.asarray(q_b, np.float64))
    cos = (np.einsum("...ij,...ij->...", R_a, R_b) - 1.0) / 2.0  # trace(R_aᵀ R_b)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def turn_warnings(idx: FloatArray, q: FloatArray, cfg: TurnConfig = TurnConfig()) -> list[str]:
    """A warning (a list of one sentence, or none) when a trajectory's orientation jumps.

    Args:
        idx: (M,) frame indices of the posed frames (any order; they are sorted; each index
            once).
        q: (M, 4) their orientations (unit quaternions of ``T_WC``).
        cfg: thresholds (module docstring).
    """
    f = np.asarray(idx, np.float64).reshape(-1)
    order = np.argsort(f, kind="stable")
    f, q = f[order], np.asarray(q, np.float64).reshape(-1, 4)[order]
    next_frame = np.diff(f) == 1  # consecutive frames; none across a span without poses
    if next_frame.sum() < cfg.min_frames:
        return []
    steps = np.where(next_frame, turn_angles_deg(q[:-1], q[1:]), 0.0)
    rate = float(np.median(steps[next_frame]))
    big = steps > max(cfg.rot_jump_factor * rate, cfg.min_rot_jump_deg)
    if not big.any():
        return []
    k = int(np.argmax(np.where(big, steps, 0.0)))
    return [
        f"the orientation jumps {steps[k]:.0f}° between posed frames {f[k]:.0f} and "
        f"{f[k + 1]:.0f} ({int(big.sum())} such step(s); median turn {rate:.2f}° per frame); "
        "orientations around a jump are not trustworthy"
    ]
