"""The SLAM system's small state types: the mode, a frame's pose record, the run counters.

Public names, in reading order: Mode, FramePose, RunStats.
"""

from __future__ import annotations

import enum
from collections import defaultdict
from dataclasses import dataclass, field

from mslam_ref.conventions import FloatArray

__all__ = ["FramePose", "Mode", "RunStats"]


class Mode(enum.IntEnum):
    """Upstream frame.py::Mode."""

    INIT = 0
    TRACKING = 1
    RELOC = 2
    TERMINATED = 3


@dataclass
class FramePose:
    """A processed frame's pose relative to keyframe ``kf``: ``T_WC = T_WC[kf] ∘ T_CkCf``.

    ``status`` is ``"keyframe"`` (the frame became keyframe ``kf``), ``"tracked"``,
    ``"relocalised"`` or ``"lost"`` (no pose; ``kf = -1``).
    """

    index: int
    timestamp: float
    kf: int
    T_CkCf: FloatArray
    status: str


@dataclass
class RunStats:
    """Counters and per-stage seconds of a run (reported in ``summary.json``)."""

    frames: int = 0
    lost_frames: int = 0
    tracking_failures: int = 0
    reloc_attempts: int = 0
    relocalisations: int = 0
    skipped_frames: int = 0
    backend_solves: int = 0
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
