"""Paper §3.3–3.4 (docs/upstream.md §1.2, §1.4, §5) — the frontend: modes, tracking, fusion, keyframes.

``SlamSystem.process(frame)`` is upstream's main-loop body for one frame, single process:

* **INIT** — ``prior.mono(frame)`` gives the first keyframe (pose = identity); mode → TRACKING.
  A prior with ``needs_parallax`` (the two-view prior: one image has no depth) instead keeps
  the first frame as a candidate and fixes it as keyframe 0, with ``X_ii`` of
  ``prior.pair(candidate, frame)``, at the first frame whose pairs with it are not degenerate
  (``prior.last_status == "ok"``); that frame becomes keyframe 1 and the frames in between
  are then tracked against the two (status ``"waiting"`` until then).
* **TRACKING** — ``prior.pair(frame, last keyframe)``, matching (initialised with the previous
  frame's ``idx_f2k``), the masks of docs/upstream.md §5.1, the IRLS Gauss–Newton on ``T_CkCf``
  (constant-position initial guess), fusion of the keyframe's pointmap (``X_kk = T_CkCf · X_kf``,
  paper Eq. 8), and the new-keyframe test (docs/upstream.md §5.5). Too few matches or a Cholesky failure
  switch to RELOC. When the pair with the last keyframe is degenerate (a prior that reports
  ``last_status``, e.g. too little parallax just after a new keyframe), the frame is tracked
  against the keyframe before it instead, and never becomes a keyframe itself; if that fails
  too and the pair with the last keyframe lacked parallax, the camera is near that keyframe,
  and the frame gets the pair's rotation with zero translation (status ``"rotation"``,
  nothing fused). When the prior reports the pair with the last keyframe as having too few
  correspondences (``last_status == "few_inliers"``: the frame is too far from it), the last
  tracked frame is made a keyframe first (late) and the frame tracked against it. A new
  keyframe triggers graph construction and the global backend **synchronously** (upstream's
  ``single_thread`` mode), or in a background thread with ``single_thread: False``
  (``mslam.system.worker``).
* **RELOC** — ``mslam.system.reloc.relocalise`` on the frame; on success mode → TRACKING.

Every frame's pose is stored *relative to a keyframe* (``T_CkCf``) and composed with the final
keyframe poses at the end (``frame_poses``), so the per-frame trajectory benefits from the
backend and from loop closures. Frames seen while lost have no pose.

Public names, in reading order:
    Mode, FramePose, RunStats, SlamSystem
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from functools import partial
from typing import Any

import numpy as np

from mslam.config import SlamConfig
from mslam.datasets.frame import Frame
from mslam.kernels import KernelSet
from mslam.system import parallax
from mslam.system.divergence import DivergenceMonitor
from mslam.system.global_opt import backend_step
from mslam.system.graph import FactorGraph, Keyframe, KeyframeStore
from mslam.system.retrieval_features import RetrievalIndex
from mslam.system.state import FramePose, Mode, RunStats
from mslam.system.worker import BackendWorker, SharedPrior
from mslam_ref import sim3
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import strided_pixels

__all__ = ["FramePose", "Mode", "RunStats", "SlamSystem"]


def _flat(a: np.ndarray) -> np.ndarray:
    return a.reshape(-1, a.shape[-1]) if a.ndim == 3 else a.reshape(-1)


def _grid_cells(idx: np.ndarray, shape: tuple[int, int], stride: int) -> np.ndarray:
    """Frame pixels ``idx`` as the indices of the ``stride`` x ``stride`` cells they fall in,
    numbered like the grid's own pixels (``strided_pixels``), so that counting distinct cells
    reached by the grid's matches is the new-keyframe test's "distinct frame pixels" at the
    grid's resolution. Identity when ``stride`` is 1."""
    if stride == 1:
        return idx
    H, W = shape
    rows, cols = len(range(stride // 2, H, stride)), len(range(stride // 2, W, stride))
    u = np.minimum((idx % W) // stride, cols - 1)
    v = np.minimum((idx // W) // stride, rows - 1)
    return u + cols * v


class SlamSystem:
    """The SLAM system of one run: keyframes, graph, retrieval, mode, per-frame poses.

    Args:
        prior: a ``Prior`` (``mono``, ``pair``).
        cfg: the resolved :class:`~mslam.config.SlamConfig`.
        kernels: the :class:`~mslam.kernels.KernelSet` (``ref`` or ``fast``).
        K: (3, 3) intrinsics at the pointmap resolution; required when ``cfg.use_calib``.
    """

    def __init__(
        self, prior: Any, cfg: SlamConfig, kernels: KernelSet, K: FloatArray | None = None
    ):
        from mslam_ref import fusion, tracking

        if cfg.use_calib and K is None:
            raise ValueError("K: calibrated mode (use_calib) needs intrinsics")
        self.cfg, self.kernels = cfg, kernels
        self.lock = threading.RLock()  # keyframes shared with the background backend
        self.worker: BackendWorker | None = None
        if cfg.single_thread:
            self.prior = prior
        else:
            self.prior = SharedPrior(prior)
            self.worker = BackendWorker(partial(backend_step, self))
        self.K = None if not cfg.use_calib else np.asarray(K, dtype=np.float64)
        self.matching_cfg = cfg.matching()
        self.tracking_cfg = cfg.tracking()
        self.fusion_cfg = cfg.fusion()
        self.backend_cfg = cfg.backend()
        self._fusion_ref, self._tracking_ref = fusion, tracking
        self.keyframes = KeyframeStore()
        self.graph = FactorGraph()
        self.retrieval = RetrievalIndex(cfg.retrieval())
        self.mode = Mode.INIT
        self.idx_f2k: np.ndarray | None = None
        self.T_WC_last = sim3.identity()
        self.poses: list[FramePose] = []
        self.stats = RunStats()
        self.backend_history: list[dict[str, Any]] = []
        self.divergence = DivergenceMonitor()  # refuses implausible poses (mslam.system.divergence)
        self._init_candidate: Frame | None = None
        self._init_pending: list[Frame] = []
        self._rotation_only: np.ndarray | None = None
        self._first_status = "ok"
        self._last_tracked: tuple | None = None
        self._tracking_pair: tuple | None = None
        from threadpoolctl import ThreadpoolController

        # Each frame runs with single-threaded BLAS: on 2 cores OpenBLAS's own threads, which
        # spin between calls, took the cores from Taichi's and OpenCV's (the descriptors'
        # products took 12 or 24 ms per 256x192 frame from run to run; whole runs 10 % slower).
        self._blas = ThreadpoolController()

    # -- bookkeeping -----------------------------------------------------------------------
    @contextmanager
    def timer(self, stage: str):
        """Add the wall time of the block to ``stats.seconds[stage]``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.stats.seconds[stage] += time.perf_counter() - t0

    def _constrain(self, X: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Points on the known rays in calibrated mode (docs/upstream.md §6.2), flat (N, 3)."""
        if self.K is None:
            return X
        from mslam_ref.calib import constrain_points_to_ray

        return constrain_points_to_ray(X.reshape(*shape, 3), self.K).reshape(-1, 3)

    def new_keyframe(
        self,
        frame: Frame,
        T_WC: FloatArray,
        X: np.ndarray,
        C: np.ndarray,
        D: np.ndarray | None = None,
        Q: np.ndarray | None = None,
    ) -> int:
        """Append a keyframe with a fresh pointmap state; returns its index."""
        shape = (int(X.shape[0]), int(X.shape[1]))
        state = self._fusion_ref.init_pointmap(_flat(X), _flat(C), self.fusion_cfg)
        if D is None or Q is None:
            with self.timer("prior"):
                p = self.prior.pair(frame, frame)
            D, Q = p.D_ii, p.Q_ii
        features = self.retrieval.features(D, Q)
        kf = Keyframe(
            frame=frame,
            T_WC=np.asarray(T_WC, np.float64).copy(),
            state=state,
            shape=shape,
            features=features,
        )
        with self.lock:
            return self.keyframes.append(kf)

    def last_pair(self) -> dict[tuple[int, int], Any]:
        """The last tracking decode, ``{(frame index, keyframe's frame index): prediction}``:
        when that frame becomes a keyframe, it is the backward decode of its consecutive
        edge, which the graph step then does not recompute."""
        if self._tracking_pair is None:
            return {}
        fi, fk, p = self._tracking_pair
        return {(fi, fk): p}

    def keyframe_added(self, k: int) -> None:
        """Run keyframe ``k``'s graph step and global solve now (default), or queue it for
        the background worker (``single_thread: False``, ``mslam.system.worker``)."""
        if self.worker is not None:
            self.worker.submit(k)
            return
        backend_step(self, k)
        self.T_WC_last = self.keyframes[k].T_WC.copy()

    def wait_for_backend(self) -> None:
        """Return once the background worker (if any) has processed every queued keyframe."""
        if self.worker is not None:
            self.worker.drain()

    def close(self) -> None:
        """Finish the queued backend work and stop the worker (the end of a run)."""
        if self.worker is not None:
            self.worker.close()

    def _record(self, frame: Frame, kf: int, T_CkCf: FloatArray | None, status: str) -> None:
        T = sim3.identity() if T_CkCf is None else np.asarray(T_CkCf, np.float64)
        self.poses.append(FramePose(int(frame.index), float(frame.timestamp), kf, T, status))

    # -- the main-loop body ----------------------------------------------------------------
    def process(self, frame: Frame) -> str:
        """Process one frame (docs/upstream.md §1.4); returns its status."""
        with self._blas.limit(limits=1, user_api="blas"):
            return self._process(frame)

    def _process(self, frame: Frame) -> str:
        self.stats.frames += 1
        if self.mode == Mode.INIT and getattr(self.prior, "needs_parallax", False):
            return parallax.init_with_parallax(self, frame)
        if self.mode == Mode.INIT:
            with self.timer("prior"):
                X, C = self.prior.mono(frame)
            k = self.new_keyframe(frame, sim3.identity(), X, C)
            self.retrieval.update(self.keyframes[k].features)
            self.T_WC_last = self.keyframes[k].T_WC.copy()
            self._record(frame, k, None, "keyframe")
            self.mode = Mode.TRACKING
            return "keyframe"
        if self.mode == Mode.RELOC:
            from mslam.system.reloc import relocalise

            self.stats.reloc_attempts += 1
            self.wait_for_backend()
            with self.timer("reloc"):
                ok = relocalise(self, frame)
            if ok:
                self.stats.relocalisations += 1
                k = len(self.keyframes) - 1
                self.T_WC_last = self.keyframes[k].T_WC.copy()
                self.idx_f2k = None
                self._record(frame, k, None, "relocalised")
                self.divergence.reset()
                self.mode = Mode.TRACKING
                return "relocalised"
            self.stats.lost_frames += 1
            self._record(frame, -1, None, "lost")
            return "lost"
        status = self.track(frame)
        if status == "lost":
            self.stats.tracking_failures += 1
            self.stats.lost_frames += 1
            self.mode = Mode.RELOC
        return status

    def _lost(self, frame: Frame) -> None:
        self.stats.lost_frames += 1
        self._record(frame, -1, None, "lost")

    def track(self, frame: Frame, allow_keyframe: bool = True, force_keyframe: bool = False) -> str:
        """Track ``frame`` against the last keyframe (upstream tracker.py::FrameTracker.track).

        ``allow_keyframe=False`` / ``force_keyframe=True`` override the new-keyframe test (used
        by the parallax-waiting INIT). Returns ``"tracked"``, ``"keyframe"`` (it became a new
        keyframe) or ``"lost"``.
        """
        tr, kr = self._tracking_ref, self.kernels
        kf_idx, p, fallback = parallax.keyframe_pair(self, frame)
        if (
            self._first_status == "few_inliers"
            and not fallback
            and allow_keyframe
            and parallax.promote_last_tracked(self)
        ):
            kf_idx, p, fallback = parallax.keyframe_pair(self, frame)
        if self._rotation_only is not None:
            return parallax.track_rotation_only(self, frame, kf_idx)
        kf = self.keyframes[kf_idx]
        self._tracking_pair = (int(frame.index), int(kf.frame.index), p)
        H, W = p.X_ii.shape[:2]
        if (H, W) != kf.shape:
            raise ValueError(f"frame {frame.index}: pointmap shape {(H, W)} != keyframe {kf.shape}")
        stride = self.cfg.tracking_pixel_stride((H, W))
        grid = strided_pixels(H, W, stride)
        X_ji = p.X_ji if stride == 1 else np.where(grid[..., None], p.X_ji, 0.0)
        with self.timer("matching"):
            idx_f2k, valid_match_k = kr.matching.match(
                p.X_ii, X_ji, p.D_ii, p.D_ji, self.idx_f2k, self.matching_cfg
            )
        idx_f2k = np.asarray(idx_f2k, np.int64)
        valid_match_k = np.asarray(valid_match_k, bool).reshape(-1)
        self.idx_f2k = idx_f2k
        # Keyframe pixels that take part: all (upstream), or the grid (tracking.pixels_per_frame).
        # In calibrated mode the solve needs the keyframe's (H, W) layout, so all are passed.
        g = np.flatnonzero(grid) if stride > 1 else slice(None)
        s = g if self.K is None else slice(None)
        with self.timer("tracking"):
            Q_k = tr.match_quality(_flat(p.Q_ii), _flat(p.Q_ji)[s], idx_f2k[s])
            state_f = self._fusion_ref.init_pointmap(_flat(p.X_ii), _flat(p.C_ii), self.fusion_cfg)
            X_f = self._constrain(state_f.X_canon, (H, W))[idx_f2k[s]]
            X_k = self._constrain(kf.state.X_canon, (H, W))[s]
            C_f = np.asarray(self._fusion_ref.average_confidence(state_f)).reshape(-1)[idx_f2k[s]]
            C_k = np.asarray(self._fusion_ref.average_confidence(kf.state)).reshape(-1)[s]
            valid_opt, valid_kf = tr.tracking_masks(
                valid_match_k[s], C_f, C_k, Q_k, self.tracking_cfg
            )
            on = slice(None) if self.K is None else g
            if float(np.mean(valid_opt[on])) < self.tracking_cfg.min_match_frac:
                self._record(frame, -1, None, "lost")
                return "lost"
            T_init = sim3.mul(sim3.inv(kf.T_WC), self.T_WC_last)
            X_k_arg = X_k.reshape(H, W, 3) if self.K is not None else X_k
            T_CkCf, info = kr.tracking.solve(
                X_f, X_k_arg, Q_k, valid_opt, T_init, self.tracking_cfg, self.K
            )
        if info.failed or not np.all(np.isfinite(T_CkCf)):
            self._record(frame, -1, None, "lost")
            return "lost"
        T_CkCf = np.asarray(T_CkCf, np.float64)
        T_WCf = sim3.mul(kf.T_WC, T_CkCf)
        if not self.divergence.check(int(frame.index), T_WCf):
            self._record(frame, -1, None, "lost")
            return "lost"
        self.T_WC_last = T_WCf
        with self.timer("fusion"):
            X_kk = sim3.act(T_CkCf, _flat(p.X_ji))
            state = kr.fusion.update_pointmap(kf.state, X_kk, _flat(p.C_ji), self.fusion_cfg)
            with self.lock:
                kf.state = state
        new_kf = bool(
            tr.needs_new_keyframe(
                _grid_cells(idx_f2k[g], (H, W), stride),
                valid_match_k[g],
                valid_kf[on],
                self.tracking_cfg,
            )
        )
        if fallback:
            self.idx_f2k = None  # the matches belong to the older keyframe
        new_kf = (new_kf or force_keyframe) and allow_keyframe and not fallback
        self._last_tracked = (frame, T_WCf, p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
        if not new_kf:
            self._record(frame, kf_idx, T_CkCf, "tracked")
            return "tracked"
        self.idx_f2k = None  # upstream reset_idx_f2k
        k = self.new_keyframe(frame, T_WCf, p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
        self._record(frame, k, None, "keyframe")
        self.keyframe_added(k)
        return "keyframe"

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
