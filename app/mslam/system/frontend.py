"""Paper §3.3–3.4, §3.6 (docs/upstream.md §1.2, §1.4, §5, §9) — the frontend state machine.

``SlamSystem.process(frame)`` is upstream's main-loop body for one frame, single process, read
top-down in :meth:`SlamSystem.step`:

* **INIT** — ``prior.mono(frame)`` gives the first keyframe (pose = identity); mode → TRACKING.
  A prior with ``needs_parallax`` (the two-view prior: one image has no depth) instead keeps
  the first frame as a candidate and fixes it as keyframe 0, with ``X_ii`` of
  ``prior.pair(candidate, frame)``, at the first frame whose pairs with it are not degenerate
  (``prior.last_status == "ok"``); that frame becomes keyframe 1 and the frames in between
  are then tracked against the two (status ``WAITING`` until then).
* **TRACKING** — the pair with the last keyframe, then :meth:`Tracker.track
  <mslam.system.tracker.Tracker.track>` (matching, masks, Gauss–Newton, fusion, the
  new-keyframe test). Too few matches or a failed solve switch to RELOC. When the pair with the
  last keyframe is degenerate (a prior that reports ``last_status``, e.g. too little parallax
  just after a new keyframe), the frame is tracked against the keyframe before it instead, and
  never becomes a keyframe itself; if that fails too and the pair with the last keyframe lacked
  parallax, the camera is near that keyframe, and the frame gets the pair's rotation with zero
  translation (``ROTATION``, nothing fused). When the prior reports the pair with the last
  keyframe as having too few correspondences (``last_status == "few_inliers"``: the frame is
  too far from it), the last tracked frame is made a keyframe first (late) and the frame
  tracked against it. A new keyframe runs the backend (:class:`~mslam.system.global_opt.Backend`)
  **synchronously** (upstream's ``single_thread`` mode), or queues it for a background thread
  with ``single_thread: False`` (``mslam.system.worker``).
* **RELOC** — :func:`mslam.system.reloc.relocalise` on the frame; on success mode → TRACKING.

Every frame's pose is stored *relative to a keyframe* (``T_CkCf``) and composed with the final
keyframe poses at the end (``frame_poses``), so the per-frame trajectory benefits from the
backend and from loop closures. Frames seen while lost have no pose.

Public names, in reading order:
    SlamSystem
"""

from __future__ import annotations

from dataclasses import dataclass

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
from mslam.system.reloc import relocalise
from mslam.system.retrieval_features import RetrievalIndex
from mslam.system.state import FramePose, FrameStatus, Mode, RunStats
from mslam.system.tracker import Tracker
from mslam.system.worker import BackendWorker, SharedPrior
from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray

__all__ = ["SlamSystem"]


def prior_status(prior: Prior) -> str:
    """The prior's verdict on its last ``pair`` ("ok" for priors that report none)."""
    return str(getattr(prior, "last_status", "ok"))


@dataclass(frozen=True)
class _KeyframePair:
    """The keyframe a frame is tracked against and the prior's decode of the pair.

    ``status`` is the prior's verdict on the pair with the *last* keyframe; ``fallback``: the
    pair is with the keyframe before it; ``R_ji``: (3, 3) the rotation to pose the frame by
    alone (no parallax and no fallback), else None.
    """

    kf_idx: int
    p: PairPrediction
    fallback: bool
    status: str
    R_ji: FloatArray | None


@dataclass(frozen=True)
class _Tracked:
    """The last tracked frame, kept in case it must become a keyframe late."""

    frame: Frame
    T_WC: FloatArray
    p: PairPrediction


class SlamSystem:
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
        self.T_WC_last = sim3.identity()
        self.poses: list[FramePose] = []
        self.init_candidate: Frame | None = None
        self.init_pending: list[Frame] = []
        self.last_tracked: _Tracked | None = None
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
        """One frame through the mode machine (module docstring)."""
        self.stats.frames += 1
        if self.mode == Mode.INIT and getattr(self.prior, "needs_parallax", False):
            return self.init_with_parallax(frame)
        if self.mode == Mode.INIT:
            return self.init_mono(frame)
        if self.mode == Mode.RELOC:
            return self.relocalise(frame)
        status = self.track(frame)
        if status == FrameStatus.LOST:
            self.lose_tracking()
        return status

    def init_mono(self, frame: Frame) -> FrameStatus:
        """INIT: the first frame's mono pointmap is keyframe 0 at the origin."""
        with self.stats.timer("prior"):
            X, C = self.prior.mono(frame)
            p = self.prior.pair(frame, frame)
        k = self.backend.add_keyframe(frame, sim3.identity(), X, C, p.D_ii, p.Q_ii)
        self.retrieval.update(self.keyframes[k].features)
        self.T_WC_last = self.keyframes[k].T_WC.copy()
        self.record(frame, k, None, FrameStatus.KEYFRAME)
        self.mode = Mode.TRACKING
        return FrameStatus.KEYFRAME

    def relocalise(self, frame: Frame) -> FrameStatus:
        """RELOC: try the frame against the map (paper §3.6)."""
        self.stats.reloc_attempts += 1
        self.wait_for_backend()
        with self.stats.timer("reloc"):
            ok = relocalise(frame, self.prior, self.backend, self.cfg.reloc)
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
        if pair.R_ji is not None:
            return self.track_rotation_only(frame, pair.kf_idx, pair.R_ji)
        kf_idx, p, fallback = pair.kf_idx, pair.p, pair.fallback
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
        self.last_tracked = _Tracked(frame, result.T_WC, p)
        if not new_kf:
            self.record(frame, kf_idx, result.T_CkCf, FrameStatus.TRACKED)
            return FrameStatus.TRACKED
        self.make_keyframe(frame, result.T_WC, p)
        return FrameStatus.KEYFRAME

    def make_keyframe(self, frame: Frame, T_WC: FloatArray, p: PairPrediction) -> int:
        """A tracked frame becomes a keyframe (its own pointmap ``X_ii``); the backend runs."""
        self.tracker.idx_f2k = None  # upstream reset_idx_f2k
        k = self.backend.add_keyframe(frame, T_WC, p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
        self.record(frame, k, None, FrameStatus.KEYFRAME)
        self.keyframe_added(k)
        return k

    # -- priors that need parallax (the two-view prior) ----------------------------------------
    def init_with_parallax(self, frame: Frame) -> FrameStatus:
        """INIT for priors without single-image depth: wait for a non-degenerate first pair.

        The first frame is the candidate; later frames wait in ``init_pending``. At the first
        frame whose pairs with the candidate are usable in both directions, the candidate
        becomes keyframe 0 (``X_ii`` of ``pair(candidate, frame)``), the frame is tracked and
        made keyframe 1, and the waiting frames are tracked against these two keyframes.
        """
        cand = self.init_candidate
        if cand is None:
            self.init_candidate, self.init_pending = frame, []
            return FrameStatus.WAITING
        with self.stats.timer("prior"):
            self.prior.pair(frame, cand)  # the direction tracking uses must be usable too
            status = prior_status(self.prior)
            p = self.prior.pair(cand, frame) if status == "ok" else None
        if p is not None:
            status = prior_status(self.prior)
        if p is None or status != "ok":
            if status == "few_inliers":  # too far apart to match: start again from here
                for f in [cand, *self.init_pending]:
                    self.stats.lost_frames += 1
                    self.record(f, -1, None, FrameStatus.LOST)
                self.init_candidate, self.init_pending = frame, []
            else:
                self.init_pending.append(frame)
            return FrameStatus.WAITING
        k = self.backend.add_keyframe(cand, sim3.identity(), p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
        self.retrieval.update(self.keyframes[k].features)
        self.T_WC_last = self.keyframes[k].T_WC.copy()
        self.record(cand, k, None, FrameStatus.KEYFRAME)
        self.mode = Mode.TRACKING
        result = self.track(frame, force_keyframe=True)
        if result == FrameStatus.LOST:
            self.lose_tracking()
        else:
            T_last = self.T_WC_last.copy()
            for f in self.init_pending:
                if self.track(f, allow_keyframe=False) == FrameStatus.LOST:
                    self.stats.lost_frames += 1
            self.T_WC_last, self.tracker.idx_f2k = T_last, None
        self.init_candidate, self.init_pending = None, []
        return result

    def keyframe_pair(self, frame: Frame) -> _KeyframePair:
        """The pair with the last keyframe, or with the one before it when the prior flags the
        first pair degenerate (``last_status``); with the rotation to pose the frame by when
        the pair with the last keyframe lacks parallax and no fallback worked."""
        kf_idx = len(self.keyframes) - 1
        with self.stats.timer("prior"):
            p = self.prior.pair(frame, self.keyframes[kf_idx].frame)
        status = prior_status(self.prior)
        if status in ("ok", "same"):
            return _KeyframePair(kf_idx, p, False, status, None)
        R_ji = getattr(self.prior, "last_R_ji", None) if status == "parallax" else None
        if kf_idx > 0:
            with self.stats.timer("prior"):
                p_prev = self.prior.pair(frame, self.keyframes[kf_idx - 1].frame)
            if prior_status(self.prior) == "ok":
                return _KeyframePair(kf_idx - 1, p_prev, True, status, None)
        return _KeyframePair(kf_idx, p, False, status, R_ji)

    def track_rotation_only(self, frame: Frame, kf_idx: int, R_ji: FloatArray) -> FrameStatus:
        """Pose a frame without parallax to its keyframe: the pair's rotation, no translation.

        With parallax below the prior's threshold the camera centre is within a small fraction
        of the scene depth from the keyframe's, so ``T_CkCf = (0, R_ji, 1)`` is off by at most
        that baseline. Nothing is fused and the frame never becomes a keyframe.
        """
        T_CkCf = np.concatenate([np.zeros(3), so3.from_matrix(R_ji), [1.0]])
        self.T_WC_last = sim3.mul(self.keyframes[kf_idx].T_WC, T_CkCf)
        self.record(frame, kf_idx, T_CkCf, FrameStatus.ROTATION)
        return FrameStatus.ROTATION

    def promote_last_tracked(self) -> bool:
        """Make the last tracked frame a keyframe (late), when the current frame is already
        too far from the last keyframe for the prior (``last_status == "few_inliers"``).

        A prior whose correspondences break down under large motion (the two-view prior's
        optical flow) can lose a keyframe before the match-fraction test asks for a new one;
        the previous frame, tracked with its own pointmap ``X_ii`` and pose, is then the
        keyframe that should have been made. Returns whether one was added.
        """
        last, self.last_tracked = self.last_tracked, None
        if last is None or last.frame.index == self.keyframes.last().frame.index:
            return False
        self.poses = [q for q in self.poses if q.index != last.frame.index]
        self.make_keyframe(last.frame, last.T_WC, last.p)
        return True

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
            return
        self.backend.step(k, self.last_pair())
        self.T_WC_last = self.keyframes[k].T_WC.copy()

    def wait_for_backend(self) -> None:
        """Return once the background worker (if any) has processed every queued keyframe."""
        if self.worker is not None:
            self.worker.drain()

    def close(self) -> None:
        """Finish the queued backend work and stop the worker (the end of a run)."""
        if self.worker is not None:
            self.worker.close()

    def record(self, frame: Frame, kf: int, T_CkCf: FloatArray | None, status: FrameStatus) -> None:
        """Append the frame's pose record (``T_CkCf`` None: the keyframe's own pose)."""
        T = sim3.identity() if T_CkCf is None else np.asarray(T_CkCf, np.float64)
        self.poses.append(FramePose(int(frame.index), float(frame.timestamp), kf, T, status))

    # -- results ---------------------------------------------------------------------------
    def frame_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses of every frame that has one, with the final keyframe poses.

        Returns:
            indices (M,) int, timestamps (M,), T_WC (M, 8) Sim(3).
        """
        rows = [p for p in self.poses if p.kf >= 0 and p.kf < len(self.keyframes)]
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
