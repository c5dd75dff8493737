"""Paper §3.3–3.4, §3.6 (docs/upstream.md §1.2, §1.4, §5, §9) — the frontend state machine.

``SlamSystem.process(frame)`` is upstream's main-loop body for one frame, single process, read
top-down in :meth:`SlamSystem.step`:

* **INIT** — ``prior.mono(frame)`` gives the first keyframe (pose = identity, or the anchor of
  a new map); mode → TRACKING.
  A prior with ``needs_parallax`` (the two-view prior: one image has no depth) instead keeps
  the first frame as a candidate and fixes it as keyframe 0, with ``X_ii`` of
  ``prior.pair(candidate, frame)``, at the first frame whose pairs with it are not degenerate
  (``prior.last_status == "ok"``); that frame becomes keyframe 1 and the frames in between
  are then tracked against the two (status ``WAITING`` until then). A camera that only turns
  never gives that pair: when the candidate's view is out of sight, the map starts without
  depth from the waiting frames' rotations (:mod:`mslam.system.rotation_start`).
* **TRACKING** — the pair with the last keyframe, then :meth:`Tracker.track
  <mslam.system.tracker.Tracker.track>` (matching, masks, Gauss–Newton, fusion, the
  new-keyframe test). Too few matches or a failed solve switch to RELOC. When the pair with the
  last keyframe is degenerate (a prior that reports ``last_status``, e.g. too little parallax
  just after a new keyframe), the frame is tracked against the keyframe before it instead, and
  never becomes a keyframe itself. When the pair with the last keyframe lacked parallax, the
  camera is near that keyframe: a frame tracked against the one before is recorded at the last
  keyframe's centre with the tracked orientation (:meth:`SlamSystem.record_near_keyframe`), and
  a frame whose fallback fails too gets the pair's rotation with zero translation (both
  ``ROTATION``; nothing fused, no keyframe asked for; :mod:`mslam.system.parallax` says when a
  pair lacks parallax). When the prior reports the pair with the last
  keyframe as having too few correspondences (``last_status == "few_inliers"``: the frame is
  too far from it), or the rotation of a frame without parallax cannot be solved, the last
  tracked frame is made a keyframe first (late) and the frame tracked against it. A new keyframe runs the backend (:class:`~mslam.system.global_opt.Backend`)
  **synchronously** (upstream's ``single_thread`` mode), or queues it for a background thread
  with ``single_thread: False`` (``mslam.system.worker``).
* **RELOC** — :func:`mslam.system.reloc.relocalise` on the frame; on success mode → TRACKING.
  When relocalisation keeps failing or poses keep being refused, a new map starts (mode →
  INIT, anchored at the last posed frame; :mod:`mslam.system.recovery`). The new map's
  keyframes look for verified connections to the map before it and, once they agree, the two
  are merged (:mod:`mslam.system.merge`).

Every frame's pose is stored *relative to a keyframe* (``T_CkCf``) and composed with the final
keyframe poses at the end (``frame_poses``), so the per-frame trajectory benefits from the
backend and from loop closures. Frames seen while lost have no pose.

Public names, in reading order:
    SlamSystem
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mslam.config import SlamConfig
from mslam.datasets.frame import Frame
from mslam.kernels import KernelSet
from mslam.priors.base import PairPrediction, Prior
from mslam.system.divergence import DivergenceMonitor
from mslam.system.edges import KnownPairs
from mslam.system.global_opt import Backend
from mslam.system.graph import FactorGraph
from mslam.system.keyframes import KeyframeStore
from mslam.system.merge import MapMerger
from mslam.system.parallax import ParallaxSteps, TrackedFrame, rotation_pose
from mslam.system.recovery import Recovery, RecoveryConfig, frame_contrast
from mslam.system.reloc import relocalise
from mslam.system.retrieval_features import RetrievalIndex
from mslam.system.rotation_start import RotationStart
from mslam.system.state import FramePose, FrameStatus, Mode, RunStats
from mslam.system.tracker import Tracker
from mslam.system.worker import BackendWorker, SharedPrior
from mslam_ref import sim3
from mslam_ref.conventions import FloatArray

__all__ = ["SlamSystem"]


class SlamSystem(ParallaxSteps, RotationStart):
    """The SLAM system of one run: the frontend's state machine over the map (``backend``).

    Args:
        prior: a :class:`~mslam.priors.base.Prior` (``mono``, ``pair``).
        cfg: the resolved :class:`~mslam.config.SlamConfig`.
        kernels: the :class:`~mslam.kernels.KernelSet` (``ref`` or ``fast``).
        K: (3, 3) intrinsics at the pointmap resolution; required when ``cfg.use_calib``.
    """

    def __init__(
        self, prior: Prior, cfg: SlamConfig, kernels: KernelSet, K: FloatArray | None = None
    ) -> None:
        if cfg.use_calib and K is None:
            raise ValueError("K: calibrated mode (use_calib) needs intrinsics")
        self.cfg, self.kernels = cfg, kernels
        self.K = None if not cfg.use_calib else np.asarray(K, dtype=np.float64)
        self.prior: Prior = prior if cfg.single_thread else SharedPrior(prior)
        self.stats = RunStats()
        self.divergence = DivergenceMonitor()  # refuses implausible poses (system.divergence)
        self.backend = Backend(cfg, kernels, self.prior, self.K, self.stats, self.divergence)
        self.tracker = Tracker(cfg, kernels, self.K, self.stats, self.backend.lock)
        self.worker = None if cfg.single_thread else BackendWorker(self.backend.step)
        self.mode = Mode.INIT
        self.recovery = Recovery(RecoveryConfig.from_sections(cfg.sections))
        self.merger = MapMerger()  # joins a new map to the one before it (system.merge)
        self.anchor = sim3.identity()  # the pose of the current map's first keyframe
        self.T_WC_last = sim3.identity()
        self.poses: list[FramePose] = []
        self.init_candidate: Frame | None = None
        self.init_pending: list[Frame] = []
        self.init_rotations: dict[int, FloatArray] = {}
        self.init_rotated_pair: PairPrediction | None = None
        self.last_tracked: TrackedFrame | None = None
        self.tracking_pair: tuple[int, int, PairPrediction] | None = None
        from threadpoolctl import ThreadpoolController

        # Each frame runs with single-threaded BLAS: on 2 cores OpenBLAS's own threads, which
        # spin between calls, took the cores from Taichi's and OpenCV's (the descriptors'
        # products took 12 or 24 ms per 256x192 frame from run to run; whole runs 10 % slower).
        self._blas = ThreadpoolController()

    # -- the map, as the backend holds it ------------------------------------------------------
    @property
    def keyframes(self) -> KeyframeStore:
        """The keyframes (``backend.keyframes``)."""
        return self.backend.keyframes

    @property
    def graph(self) -> FactorGraph:
        """The factor graph (``backend.graph``)."""
        return self.backend.graph

    @property
    def retrieval(self) -> RetrievalIndex:
        """The retrieval index (``backend.retrieval``)."""
        return self.backend.retrieval

    # -- the main-loop body ----------------------------------------------------------------
    def process(self, frame: Frame) -> FrameStatus:
        """Process one frame (docs/upstream.md §1.4); returns its status."""
        with self._blas.limit(limits=1, user_api="blas"):
            return self.step(frame)

    def step(self, frame: Frame) -> FrameStatus:
        """One frame through the mode machine (module docstring), then the recovery test."""
        self.stats.frames += 1
        if self.mode == Mode.INIT and getattr(self.prior, "needs_parallax", False):
            status = self.wait_if_still(frame) or self.init_with_parallax(frame)
        elif self.mode == Mode.INIT:
            status = self.init_mono(frame)
        elif self.mode == Mode.RELOC:
            status = self.relocalise(frame)
        else:
            status = self.track(frame)
            if status == FrameStatus.LOST:
                self.lose_tracking()
        refused = self.divergence.refused_frames()
        why = self.recovery.after_frame(
            int(frame.index), status, refused, frame_contrast(frame.rgb)
        )
        if why is not None and self.mode != Mode.INIT:
            self.start_new_map(frame, why)
        return status

    def wait_if_still(self, frame: Frame) -> FrameStatus | None:
        """INIT for priors that need parallax: a frame whose image is the waiting candidate's,
        pixel for pixel (a camera at rest, a video encoder repeating a frame), shows the same
        view; it waits with the candidate and is posed with the other waiting frames. A prior
        may call such a pair unmatched (no correspondence survives a zero-motion model fit),
        which would restart the wait from the frame and leave the earlier ones unposed.
        Returns ``WAITING``, or None for any other frame."""
        cand = self.init_candidate
        if cand is None or not np.array_equal(frame.rgb, cand.rgb):
            return None
        self.init_pending.append(frame)
        return FrameStatus.WAITING

    def start_new_map(self, frame: Frame, reason: str) -> None:
        """Give the current map up (``mslam.system.recovery``): the next frames initialise a
        new map whose first keyframe takes the final pose of the last posed frame."""
        self.wait_for_backend()
        _, _, T = self.frame_poses()
        if len(T):
            self.anchor = T[-1].copy()
        self.backend.start_map()
        self.recovery.new_map(int(frame.index), len(self.keyframes), reason)
        self.divergence.new_map()
        self.merger.reset()
        self.tracker.idx_f2k, self.last_tracked = None, None
        self.restart_wait(None)
        self.mode = Mode.INIT

    def init_mono(self, frame: Frame) -> FrameStatus:
        """INIT: the first frame's mono pointmap is keyframe 0 at the origin."""
        with self.stats.timer("prior"):
            X, C = self.prior.mono(frame)
            p = self.prior.pair(frame, frame)
        k = self.backend.add_keyframe(frame, self.anchor, X, C, p.D_ii, p.Q_ii)
        self.retrieval.update(self.keyframes[k].retrieval_features())
        self.T_WC_last = self.keyframes[k].T_WC.copy()
        self.record(frame, k, None, FrameStatus.KEYFRAME)
        self.mode = Mode.TRACKING
        return FrameStatus.KEYFRAME

    def relocalise(self, frame: Frame) -> FrameStatus:
        """RELOC: try the frame against the map (paper §3.6)."""
        self.stats.reloc_attempts += 1
        self.wait_for_backend()
        with self.stats.timer("reloc"):
            ok = relocalise(
                frame, self.prior, self.backend, self.cfg.reloc, self.place_relocalised,
                self.rotation_match if getattr(self.prior, "needs_parallax", False) else None,
                self.rejoin_map if self.recovery.cfg.merge_maps else None,
            )  # fmt: skip
        if not ok:
            self.stats.lost_frames += 1
            self.record(frame, -1, None, FrameStatus.LOST)
            return FrameStatus.LOST
        self.stats.relocalisations += 1
        k = len(self.keyframes) - 1
        self.T_WC_last = self.keyframes[k].T_WC.copy()
        self.tracker.idx_f2k = None
        self.divergence.reset()
        self.record(frame, k, None, FrameStatus.RELOCALISED)
        self.mode = Mode.TRACKING
        return FrameStatus.RELOCALISED

    def rejoin_map(self, k: int, best: int) -> None:
        """Relocalised against keyframe ``best`` of another map: new keyframe ``k`` starts a
        map that continues ``best``'s segment (``Recovery.rejoined``), and the backend reaches
        back to it (``Recovery.layout``); the current map is left as it stands."""
        self.recovery.rejoined(int(self.keyframes[k].frame.index), k, best)
        self.backend.join_map(*self.recovery.layout())
        self.divergence.new_map()
        self.merger.reset()

    def lose_tracking(self) -> None:
        """Count a tracking failure and switch to relocalisation."""
        self.stats.tracking_failures += 1
        self.stats.lost_frames += 1
        self.mode = Mode.RELOC

    def track(
        self, frame: Frame, allow_keyframe: bool = True, force_keyframe: bool = False
    ) -> FrameStatus:
        """Track ``frame`` against the last keyframe, and make it a keyframe if due.

        Upstream: tracker.py::FrameTracker.track with main.py's keyframe step.
        ``allow_keyframe=False`` / ``force_keyframe=True`` override the new-keyframe test (used
        by the parallax-waiting INIT).
        """
        pair = self.keyframe_pair(frame)
        if pair.status == "few_inliers" and not pair.fallback and allow_keyframe:
            if self.promote_last_tracked():
                pair = self.keyframe_pair(frame)
        if pair.status == "parallax" and not pair.fallback:
            rotated = self.track_rotation_only(frame, pair)
            if rotated is None and allow_keyframe and self.promote_last_tracked():
                return self.track(frame, allow_keyframe=False)  # against the promoted frame
            if rotated is None:
                self.record(frame, -1, None, FrameStatus.LOST)
            return FrameStatus.LOST if rotated is None else rotated
        kf_idx, p, fallback = pair.kf_idx, pair.p, pair.fallback
        self.seed_depth(kf_idx, frame)  # a keyframe made under pure rotation (rotation_start)
        kf = self.keyframes[kf_idx]
        self.tracking_pair = (int(frame.index), int(kf.frame.index), p)
        result = self.tracker.track(
            kf, p, self.T_WC_last, lambda T_WC: self.divergence.check(int(frame.index), T_WC)
        )
        if result is None:
            self.record(frame, -1, None, FrameStatus.LOST)
            return FrameStatus.LOST
        self.T_WC_last = result.T_WC
        if fallback:
            self.tracker.idx_f2k = None  # the matches belong to the older keyframe
        new_kf = (result.wants_keyframe or force_keyframe) and allow_keyframe and not fallback
        self.last_tracked = TrackedFrame(frame, result.T_WC, p)
        if fallback and pair.status == "parallax":
            return self.record_near_keyframe(frame, result.T_WC)
        if not new_kf:
            self.record(frame, kf_idx, result.T_CkCf, FrameStatus.TRACKED)
            return FrameStatus.TRACKED
        self.make_keyframe(frame, result.T_WC, p)
        return FrameStatus.KEYFRAME

    def record_near_keyframe(self, frame: Frame, T_WC: FloatArray) -> FrameStatus:
        """Record a frame without parallax to the last keyframe, tracked against the one
        before it (``T_WC``), as the last keyframe's rotation: ``T_CkCf = (0, R, 1)``.

        The pair with the last keyframe says the camera centre is within a small fraction of
        the scene depth of that keyframe's, so its centre is the better position; the
        tracking against the older keyframe, over a wider baseline whose relative pose the
        backend later moves, put such frames 3–7 cm from their neighbours on the 7-Scenes
        kitchen clip (2026-11-27). The tracked pose still serves the frontend (the next
        frame's start, a late keyframe); only the recorded pose changes.
        """
        last = len(self.keyframes) - 1
        q = sim3.mul(sim3.inv(self.keyframes[last].T_WC), T_WC)[3:7]
        self.record(frame, last, rotation_pose(q), FrameStatus.ROTATION)
        return FrameStatus.ROTATION

    def make_keyframe(self, frame: Frame, T_WC: FloatArray, p: PairPrediction) -> int:
        """A tracked frame becomes a keyframe (its own pointmap ``X_ii``); the backend runs."""
        self.tracker.idx_f2k = None  # upstream reset_idx_f2k
        k = self.backend.add_keyframe(frame, T_WC, p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
        self.record(frame, k, None, FrameStatus.KEYFRAME)
        self.keyframe_added(k)
        return k

    # -- the backend -----------------------------------------------------------------------
    def last_pair(self) -> KnownPairs:
        """The last tracking decode, ``{(frame index, keyframe's frame index): prediction}``:
        when that frame becomes a keyframe, it is the backward decode of its consecutive
        edge, which the graph step then does not recompute."""
        if self.tracking_pair is None:
            return {}
        fi, fk, p = self.tracking_pair
        return {(fi, fk): p}

    def keyframe_added(self, k: int) -> None:
        """Run keyframe ``k``'s graph step and global solve now (default), or queue it for
        the background worker (``single_thread: False``, ``mslam.system.worker``)."""
        if self.worker is not None:
            self.worker.submit(k, self.last_pair())
        else:
            self.backend.step(k, self.last_pair())
            self.T_WC_last = self.keyframes[k].T_WC.copy()
        if self.backend.map_start > 0:
            self.merge_maps(k)

    def merge_maps(self, k: int) -> None:
        """In a map after the first, look for connections of keyframe ``k`` to the map before
        it and merge the two when they agree (:mod:`mslam.system.merge`; with the worker, its
        queue is drained first); the frontend's world-frame poses follow the correction."""
        self.wait_for_backend()
        S = self.merger.step(self.backend, self.recovery, k, self.cfg.reloc.min_match_frac)
        if S is None:
            return
        self.T_WC_last = sim3.mul(S, self.T_WC_last)
        if self.last_tracked is not None:
            self.last_tracked = replace(self.last_tracked, T_WC=sim3.mul(S, self.last_tracked.T_WC))
        self.divergence.reset()  # the path continues in the earlier map's frame

    def pair_partner(self) -> Frame | None:
        """The frame the next frame will most likely be paired with, for the prior's
        prefetch: the last keyframe while tracking, the waiting candidate in INIT."""
        if self.mode == Mode.TRACKING and len(self.keyframes):
            return self.keyframes[-1].frame
        return self.init_candidate if self.mode == Mode.INIT else None

    def wait_for_backend(self) -> None:
        """Return once the background worker (if any) has processed every queued keyframe."""
        if self.worker is not None:
            self.worker.drain()

    def close(self) -> None:
        """Pose the frames still waiting for parallax by rotation when they can be
        (``RotationStart.finish_waiting``), finish the queued backend work and stop the worker
        (the end of a run)."""
        self.finish_waiting()
        if self.worker is not None:
            self.worker.close()

    def record(self, frame: Frame, kf: int, T_CkCf: FloatArray | None, status: FrameStatus) -> None:
        """Append the frame's pose record (``T_CkCf`` None: the keyframe's own pose)."""
        T = sim3.identity() if T_CkCf is None else np.asarray(T_CkCf, np.float64)
        self.poses.append(FramePose(int(frame.index), float(frame.timestamp), kf, T, status))

    # -- results ---------------------------------------------------------------------------
    def frame_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses of every frame that has one, with the final keyframe poses, in frame order
        (frames that waited for parallax are posed after the frame that ended the wait; TUM
        tools expect ascending stamps, and paths and turns are measured between neighbours).

        Returns:
            indices (M,) int, timestamps (M,), T_WC (M, 8) Sim(3).
        """
        rows = [p for p in self.poses if p.kf >= 0 and p.kf < len(self.keyframes)]
        rows.sort(key=lambda p: p.index)
        if not rows:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 8))
        T_kf = self.keyframes.poses()
        T = sim3.mul(T_kf[[p.kf for p in rows]], np.stack([p.T_CkCf for p in rows]))
        return (
            np.array([p.index for p in rows], np.int64),
            np.array([p.timestamp for p in rows]),
            T,
        )

    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keyframe frame indices (K,), timestamps (K,) and poses (K, 8)."""
        idx = np.array([kf.frame.index for kf in self.keyframes], np.int64)
        ts = np.array([kf.frame.timestamp for kf in self.keyframes], np.float64)
        return idx, ts, self.keyframes.poses()
