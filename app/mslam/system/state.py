"""The SLAM system's small state types: the mode, a frame's status and pose record, the counters.

Public names, in reading order: Mode, FrameStatus, FramePose, RunStats.
"""

from __future__ import annotations

import enum
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from mslam_ref.conventions import FloatArray

__all__ = ["FramePose", "FrameStatus", "Mode", "RunStats"]


class Mode(enum.IntEnum):
    """Upstream frame.py::Mode."""

    INIT = 0
    TRACKING = 1
    RELOC = 2
    TERMINATED = 3


class FrameStatus(enum.StrEnum):
    """What became of one frame; the value is the word written to outputs and logs.

    A ``StrEnum``: ``FrameStatus.LOST == "lost"``, and JSON writes the word.
    """

    #: The frame became a keyframe (its pose is the keyframe's).
    KEYFRAME = "keyframe"
    #: Tracked against a keyframe (pose ``T_CkCf`` relative to it).
    TRACKED = "tracked"
    #: Posed by the pair's rotation alone, no translation (too little parallax, two-view prior).
    ROTATION = "rotation"
    #: Posed again after tracking was lost (paper §3.6).
    RELOCALISED = "relocalised"
    #: No pose.
    LOST = "lost"
    #: Held back until the first two keyframes exist (a prior that needs parallax).
    WAITING = "waiting"


@dataclass
class FramePose:
    """A processed frame's pose relative to keyframe ``kf``: ``T_WC = T_WC[kf] ∘ T_CkCf``.

    ``status`` is a :class:`FrameStatus`: ``KEYFRAME`` (the frame became keyframe ``kf``),
    ``TRACKED``, ``ROTATION``, ``RELOCALISED`` or ``LOST`` (no pose; ``kf = -1``).
    """

    index: int
    timestamp: float
    kf: int
    T_CkCf: FloatArray
    status: FrameStatus


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

    @contextmanager
    def timer(self, stage: str) -> Iterator[None]:
        """Add the wall time of the block to ``seconds[stage]``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - t0
