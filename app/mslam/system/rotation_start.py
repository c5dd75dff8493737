"""Paper §3.3 (docs/upstream.md §1.4) — a map that starts under pure rotation, for priors that
need parallax.

The two-view prior (``mslam.priors.twoview``) has no depth without parallax, and the frontend
waits for a first pair with parallax before it fixes keyframe 0
(:meth:`~mslam.system.parallax.ParallaxSteps.init_with_parallax`). A camera that only turns
(a pan from a tripod, a phone turned in place) never gives that pair: the candidate's overlap
runs out and its waiting frames would be lost. Instead, the frames the prior found to be
turned from the candidate without parallax (``last_status == "parallax"``, ``last_R_ji`` their
rotation) are kept with their rotations, and when the overlap runs out
(:meth:`RotationStart.start_by_rotation`):

* the candidate becomes keyframe 0 *without depth* (the prior's ``mono``: a plane with
  ``C = NO_INFO_C``), the waiting frames are posed by their rotations about its centre
  (``ROTATION``), and tracking goes on as after any keyframe: frames without parallax are
  posed by rotation, a loss of overlap makes the last of them a keyframe (its pointmap the
  keyframe's seen through its rays: still without depth);
* a keyframe without depth (:func:`depthless`) gets depth from the first pair with parallax
  it is tracked in (:meth:`RotationStart.seed_depth`: ``X_ii`` of ``pair(keyframe, frame)``,
  as keyframe 0 gets it at a parallax start), so tracking never aligns a frame to a plane;
* relocalisation against keyframes without depth cannot use edges (no confident points):
  a candidate whose pair with the frame is a rotation (:meth:`RotationStart.rotation_match`)
  is accepted and the frame placed by that rotation about its centre
  (``ParallaxSteps.place_relocalised``).

Public names, in reading order:
    depthless, RotationStart
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mslam.datasets.frame import Frame
from mslam.priors.base import NO_INFO_C, PairPrediction, Prior
from mslam.system.global_opt import Backend
from mslam.system.keyframes import Keyframe
from mslam.system.parallax import TrackedFrame, replace_pointmap, rotation_pose
from mslam.system.state import FrameStatus, Mode, RunStats
from mslam_ref import fusion, sim3, so3
from mslam_ref.conventions import FloatArray

__all__ = ["RotationStart", "depthless"]


def depthless(kf: Keyframe) -> bool:
    """Whether no point of the keyframe has more than ``NO_INFO_C`` confidence (no depth)."""
    return float(np.max(fusion.average_confidence(kf.state))) <= NO_INFO_C


class RotationStart:
    """The steps of the module docstring; a mixin that only ``SlamSystem`` inherits, which owns
    these fields (``init_rotations``: waiting frame index -> its rotation to the candidate
    ``R`` (3, 3); ``init_rotated_pair``: the prediction of the latest such frame's pair, the
    one frame that may become a keyframe late)."""

    prior: Prior
    stats: RunStats
    backend: Backend
    mode: Mode
    anchor: FloatArray
    T_WC_last: FloatArray
    init_candidate: Frame | None
    init_pending: list[Frame]
    init_rotations: dict[int, FloatArray]
    init_rotated_pair: PairPrediction | None
    last_tracked: TrackedFrame | None
    record: Callable[..., None]
    track: Callable[..., FrameStatus]
    lose_tracking: Callable[[], None]
    pair_status: Callable[[PairPrediction], str]
    restart_wait: Callable[[Frame | None], None]

    def start_by_rotation(self, frame: Frame | None) -> FrameStatus | None:
        """Start the map from the waiting candidate without depth (module docstring) when
        some waiting frames were posed by rotation; returns the status of ``frame`` (tracked
        after them; ``ROTATION`` when ``frame`` is None: the sequence ended), or None (nothing
        started) when none was."""
        cand = self.init_candidate
        if cand is None or not any(f.index in self.init_rotations for f in self.init_pending):
            return None
        with self.stats.timer("prior"):
            X, C = self.prior.mono(cand)
            p = self.prior.pair(cand, cand)
        k = self.backend.add_keyframe(cand, self.anchor, X, C, p.D_ii, p.Q_ii)
        self.backend.retrieval.update(self.backend.keyframes[k].retrieval_features())
        self.record(cand, k, None, FrameStatus.KEYFRAME)
        self.T_WC_last = self.backend.keyframes[k].T_WC.copy()
        for f in self.init_pending:
            self._pose_waiting(f, k)
        last = [f for f in self.init_pending if f.index in self.init_rotations][-1]
        if self.init_rotated_pair is not None:  # it may become a keyframe (promote_last_tracked)
            R = self.init_rotations[last.index]
            self.last_tracked = TrackedFrame(last, self.T_WC_last, self.init_rotated_pair, k, R)
        self.restart_wait(None)
        self.mode = Mode.TRACKING
        if frame is None:
            return FrameStatus.ROTATION
        result = self.track(frame)
        if result == FrameStatus.LOST:
            self.lose_tracking()
        return result

    def _pose_waiting(self, f: Frame, k: int) -> None:
        """Record waiting frame ``f`` against keyframe ``k`` (the candidate): by its rotation,
        at the candidate's pose when its image is the candidate's, else lost."""
        T_W0 = self.backend.keyframes[k].T_WC
        if f.index in self.init_rotations:
            T_CkCf = rotation_pose(so3.from_matrix(self.init_rotations[f.index]))
            self.T_WC_last = sim3.mul(T_W0, T_CkCf)
            self.record(f, k, T_CkCf, FrameStatus.ROTATION)
        elif np.array_equal(f.rgb, self.backend.keyframes[k].frame.rgb):  # a still frame
            self.record(f, k, None, FrameStatus.ROTATION)
        else:
            self.stats.lost_frames += 1
            self.record(f, -1, None, FrameStatus.LOST)

    def finish_waiting(self) -> None:
        """At the end of the sequence, pose the frames still waiting for parallax by their
        rotations (:meth:`start_by_rotation`), when they have any: a short pan from a tripod
        is posed, not lost. Frames that stay unposed are recorded and counted as lost, so
        that every frame is posed, lost or skipped."""
        if self.mode == Mode.INIT and self.init_candidate is not None:
            if self.start_by_rotation(None) is None:
                self.lose_waiting()
                self.restart_wait(None)

    def lose_waiting(self) -> None:
        """Record the waiting candidate and the frames waiting with it as lost (counted)."""
        for f in [self.init_candidate, *self.init_pending]:
            if f is not None:
                self.stats.lost_frames += 1
                self.record(f, -1, None, FrameStatus.LOST)

    def seed_depth(self, kf_idx: int, frame: Frame) -> None:
        """Give keyframe ``kf_idx`` the depth of its pair with ``frame`` when it has none and
        the pair has parallax (module docstring); otherwise nothing changes."""
        kf = self.backend.keyframes[kf_idx]
        if not getattr(self.prior, "needs_parallax", False) or not depthless(kf):
            return
        with self.stats.timer("prior"):
            p = self.prior.pair(kf.frame, frame)
        if self.pair_status(p) != "ok":
            return
        X, C = np.asarray(p.X_ii, np.float64), np.asarray(p.C_ii, np.float64)
        replace_pointmap(self.backend, kf, X, C)

    def rotation_match(self, n: int, c: int) -> bool:
        """Whether keyframe ``n``'s image is turned from keyframe ``c``'s without parallax, as
        the prior sees the pair (``"parallax"`` with a rotation), when ``c`` has no depth:
        relocalisation's test for such a candidate (module docstring)."""
        if not depthless(self.backend.keyframes[c]):
            return False
        with self.stats.timer("prior"):
            p = self.prior.pair(self.backend.keyframes[n].frame, self.backend.keyframes[c].frame)
        R = getattr(self.prior, "last_R_ji", None)
        return self.pair_status(p) == "parallax" and R is not None
