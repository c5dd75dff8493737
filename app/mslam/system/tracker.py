"""Paper §3.3 (docs/upstream.md §1.4, §5) — tracking one frame against its keyframe, and fusion.

:meth:`Tracker.track` is upstream's ``FrameTracker.track`` for one frame, given the prior's
decode of the pair (frame, keyframe) in the keyframe's camera:

1. matching (paper §3.2) of the frame's points into the keyframe, initialised with the previous
   frame's ``idx_f2k``;
2. the masks of docs/upstream.md §5.1 (match, confidence and quality); when the confidence
   threshold ``C_conf`` leaves fewer than ``min_match_frac`` of the pixels, every matched
   pixel of sufficient quality is used instead (the frame is not lost for it);
3. the IRLS Gauss–Newton on ``T_CkCf`` (ray+distance, or calibrated pixels+depth), from the
   constant-position guess;
4. fusion of the keyframe's canonical pointmap with ``X_kk = T_CkCf · X_kf`` (paper Eq. 8),
   and of the map's copy of it (``Keyframe.X_map``) with filled-in points (``C = NO_INFO_C``)
   kept out of the average (:func:`without_filler`);
5. the new-keyframe test (docs/upstream.md §5.5) as a recommendation to the caller; with
   ``tracking.keyframe_first_ratio`` its threshold is capped relative to the overlap of the
   first frame tracked against the keyframe (:meth:`Tracker._keyframe_threshold`).

Too few valid matches or a failed solve mean the frame is lost (``None``).

Public names, in reading order:
    without_filler, TrackResult, Tracker
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from mslam.config import SlamConfig
from mslam.kernels import KernelSet
from mslam.priors.base import NO_INFO_C, PairPrediction
from mslam.system.keyframes import Keyframe
from mslam.system.state import RunStats
from mslam_ref import fusion, sim3, tracking
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import strided_pixels

__all__ = ["TrackResult", "Tracker", "without_filler"]


def flat(a: np.ndarray) -> np.ndarray:
    """(H, W, ...) -> (H·W, ...): a pointmap or per-pixel array as one row per pixel."""
    return a.reshape(-1, a.shape[-1]) if a.ndim == 3 else a.reshape(-1)


def grid_cells(idx: np.ndarray, shape: tuple[int, int], stride: int) -> np.ndarray:
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


def constrain(X: np.ndarray, shape: tuple[int, int], K: FloatArray | None) -> np.ndarray:
    """Points on the known rays in calibrated mode (docs/upstream.md §6.2), flat (N, 3)."""
    if K is None:
        return X
    from mslam_ref.calib import constrain_points_to_ray

    return constrain_points_to_ray(X.reshape(*shape, 3), K).reshape(-1, 3)


def without_filler(
    state: fusion.PointmapState, X: FloatArray, C: FloatArray
) -> tuple[fusion.PointmapState, FloatArray]:
    """Keep points without a measurement (``C <= NO_INFO_C``) out of the fused positions.

    Used for the map's copy of the canonical pointmap (``Keyframe.X_map``, what
    ``reconstruction.ply`` exports); tracking and the backend keep upstream's average.

    A prior fills pixels it cannot measure (RGB-D pixels without depth, two-view pixels that
    failed triangulation) with a neighbour's depth and ``C = NO_INFO_C``. Averaged in, a filled
    point would pull a measured one towards the neighbour's depth with weight ``1 / (C + 1)``;
    so before the update (``fusion.update_pointmap``, any filtering mode):

    * a new point with ``C <= NO_INFO_C`` is replaced by the canonical point (the average does
      not move; its confidence still counts in ``C`` and ``N``, so ``C / N`` drops);
    * a canonical pixel that has only seen filled points (``C / N <= NO_INFO_C``) takes the new
      measured point, which the weighted average then returns exactly.

    A pixel that was never measured keeps ``C / N = NO_INFO_C`` and is never exported.

    Args:
        state: the keyframe's canonical pointmap, X_canon (P, 3), C (P,).
        X: (P, 3) the new points in the keyframe's camera; C: (P,) their confidences.

    Returns:
        the state to update (a copy where it changed) and the points to fuse (P, 3).
    """
    new_filled = np.asarray(C).reshape(-1) <= NO_INFO_C
    old_filled = np.asarray(fusion.average_confidence(state)).reshape(-1) <= NO_INFO_C
    take = old_filled & ~new_filled
    if take.any():
        state = replace(state, X_canon=np.where(take[:, None], X, state.X_canon))
    if new_filled.any():
        X = np.where(new_filled[:, None], state.X_canon, X)
    return state, X


@dataclass(frozen=True)
class TrackResult:
    """A tracked frame: its pose relative to the keyframe and the new-keyframe test's answer.

    Attributes:
        T_CkCf: (8,) Sim(3) frame-to-keyframe pose.
        T_WC: (8,) the frame's world pose ``T_WC[kf] ∘ T_CkCf``.
        wants_keyframe: the new-keyframe test (docs/upstream.md §5.5) asks for a keyframe.
    """

    T_CkCf: FloatArray
    T_WC: FloatArray
    wants_keyframe: bool


class Tracker:
    """Tracks frames against keyframes (module docstring); keeps the last ``idx_f2k``.

    Args:
        cfg: the run configuration (matching, tracking, fusion, pixel grid).
        kernels: the kernel set (``matching.match``, ``tracking.solve``,
            ``fusion.update_pointmap``).
        K: (3, 3) intrinsics in calibrated mode, else None.
        stats: the run's counters (stage timers).
        lock: guards the keyframe's pointmap against the background backend.
    """

    def __init__(
        self,
        cfg: SlamConfig,
        kernels: KernelSet,
        K: FloatArray | None,
        stats: RunStats,
        lock: threading.RLock,
    ) -> None:
        self.cfg, self.kernels, self.K, self.stats, self.lock = cfg, kernels, K, stats, lock
        self.matching_cfg = cfg.matching()
        self.tracking_cfg = cfg.tracking()
        self.fusion_cfg = cfg.fusion()
        #: (H·W,) for every keyframe pixel, its match in the last frame (upstream ``idx_f2k``).
        self.idx_f2k: np.ndarray | None = None
        #: (keyframe's frame index, the overlap of the first frame tracked against it).
        self._first_overlap: tuple[int, float] | None = None
        # With the fast kernels, matching and fusion keep the keyframe's descriptors and fused
        # pointmap on the device between frames (mslam_fast.resident); same results.
        res = kernels.resident
        self._match_fn = res.ResidentMatcher().match if res else kernels.matching.match
        self._fuse_fn = (
            res.ResidentFusion().update_pointmap if res else kernels.fusion.update_pointmap
        )

    def track(
        self,
        kf: Keyframe,
        p: PairPrediction,
        T_WC_last: FloatArray,
        plausible: Callable[[FloatArray], bool] | None = None,
        fuse: bool = True,
    ) -> TrackResult | None:
        """Track one frame against ``kf`` given the decode ``p = prior.pair(frame, kf)``.

        Upstream: tracker.py::FrameTracker.track. Fuses the frame into ``kf``'s pointmap.

        Args:
            kf: the keyframe.
            p: the pair's decode in the keyframe's camera.
            T_WC_last: (8,) the last frame's world pose (the constant-position guess).
            plausible: ``T_WC -> bool``, the divergence watch; a refused pose is not fused
                and the frame is lost (``mslam.system.divergence``).
            fuse: False leaves the keyframe's pointmap as it is (a pose for its rotation only,
                ``mslam.system.parallax``).

        Returns:
            the pose and the keyframe test's answer, or None when the frame is lost.
        """
        H, W = p.X_ii.shape[:2]
        if (H, W) != kf.shape:
            raise ValueError(f"pointmap shape {(H, W)} != keyframe {kf.shape}")
        stride = self.cfg.tracking_pixel_stride((H, W))
        grid = strided_pixels(H, W, stride)
        idx_f2k, valid_match_k = self._match(p, grid, stride)
        # Keyframe pixels that take part: all (upstream), or the grid (tracking.pixels_per_frame).
        # In calibrated mode the solve needs the keyframe's (H, W) layout, so all are passed.
        g = np.flatnonzero(grid) if stride > 1 else slice(None)
        s = g if self.K is None else slice(None)
        on = slice(None) if self.K is None else g
        cfg = self.tracking_cfg
        with self.stats.timer("tracking"):
            Q_k = tracking.match_quality(flat(p.Q_ii), flat(p.Q_ji)[s], idx_f2k[s])
            state_f = fusion.init_pointmap(flat(p.X_ii), flat(p.C_ii), self.fusion_cfg)
            X_f = constrain(state_f.X_canon, (H, W), self.K)[idx_f2k[s]]
            X_k = constrain(kf.state.X_canon, (H, W), self.K)[s]
            C_f = np.asarray(fusion.average_confidence(state_f)).reshape(-1)[idx_f2k[s]]
            C_k = np.asarray(fusion.average_confidence(kf.state)).reshape(-1)[s]
            valid_opt, valid_kf = tracking.tracking_masks(valid_match_k[s], C_f, C_k, Q_k, cfg)
            if float(np.mean(valid_opt[on])) < cfg.min_match_frac and cfg.C_conf > 0:
                # Too few confident pixels (e.g. a prior that triangulated little of a narrow
                # view): the frame is tracked on every matched pixel rather than lost.
                cfg = replace(cfg, C_conf=0.0)
                valid_opt, valid_kf = tracking.tracking_masks(valid_match_k[s], C_f, C_k, Q_k, cfg)
            if float(np.mean(valid_opt[on])) < cfg.min_match_frac:
                return None
            T_init = sim3.mul(sim3.inv(kf.T_WC), T_WC_last)
            X_k_arg = X_k.reshape(H, W, 3) if self.K is not None else X_k
            T_CkCf, info = self.kernels.tracking.solve(
                X_f, X_k_arg, Q_k, valid_opt, T_init, cfg, self.K
            )
        if info.failed or not np.all(np.isfinite(T_CkCf)):
            return None
        T_CkCf = np.asarray(T_CkCf, np.float64)
        T_WC = sim3.mul(kf.T_WC, T_CkCf)
        if plausible is not None and not plausible(T_WC):
            return None
        if fuse:
            self._fuse(kf, p, T_CkCf)
        cell = self.cfg.keyframe_cell_stride((H, W))
        n_cells = len(range(cell // 2, H, cell)) * len(range(cell // 2, W, cell))
        cells_f = grid_cells(idx_f2k[g], (H, W), cell)
        thresh = self._keyframe_threshold(kf, cells_f, valid_match_k[g], valid_kf[on], n_cells)
        wants = tracking.needs_new_keyframe(
            cells_f, valid_match_k[g], valid_kf[on], replace(cfg, match_frac_thresh=thresh), n_cells
        )
        return TrackResult(T_CkCf, T_WC, bool(wants))

    def _keyframe_threshold(
        self,
        kf: Keyframe,
        cells_f: np.ndarray,
        valid_match_k: np.ndarray,
        valid_kf: np.ndarray,
        n_cells: int,
    ) -> float:
        """The new-keyframe test's threshold for this frame: ``match_frac_thresh``, or less
        where the keyframe's first tracked frame already saw little of it.

        The test's overlap (``tracking.keyframe_overlap``) is below 1 even next to the
        keyframe: pixels whose points fail the matcher's occlusion test (far depth noisier than
        ``matching.dist_thresh``) or matches that the descriptor refinement pulls onto the same
        frame pixel (blurred, compressed or low-texture images). Where that first overlap is
        under the threshold, every frame would become a keyframe. With
        ``tracking.keyframe_first_ratio`` r > 0 the threshold is ``min(match_frac_thresh,
        r · overlap_first)``, ``overlap_first`` the overlap of the first frame tracked against
        ``kf`` (docs/system.md, the RGB-D config; benchmarks/RESULTS.md, "A keyframe's first
        frame")."""
        thresh = float(self.tracking_cfg.match_frac_thresh)
        ratio = self.cfg.keyframe_first_ratio()
        if ratio <= 0:
            return thresh
        key = int(kf.frame.index)
        if self._first_overlap is None or self._first_overlap[0] != key:
            first = tracking.keyframe_overlap(cells_f, valid_match_k, valid_kf, n_cells)
            self._first_overlap = (key, first)
        return min(thresh, ratio * self._first_overlap[1])

    def _match(
        self, p: PairPrediction, grid: np.ndarray, stride: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Matching of the frame into the keyframe (paper §3.2), on the tracking grid."""
        X_ji = p.X_ji if stride == 1 else np.where(grid[..., None], p.X_ji, 0.0)
        with self.stats.timer("matching"):
            idx_f2k, valid_match_k = self._match_fn(
                p.X_ii, X_ji, p.D_ii, p.D_ji, self.idx_f2k, self.matching_cfg
            )
        self.idx_f2k = np.asarray(idx_f2k, np.int64)
        return self.idx_f2k, np.asarray(valid_match_k, bool).reshape(-1)

    def _fuse(self, kf: Keyframe, p: PairPrediction, T_CkCf: FloatArray) -> None:
        """Fuse the frame's points, moved into the keyframe, into its pointmap (paper Eq. 8)."""
        with self.stats.timer("fusion"):
            X_kk, C_kk = sim3.act(T_CkCf, flat(p.X_ji)), flat(p.C_ji)
            state = self._fuse_fn(kf.state, X_kk, C_kk, self.fusion_cfg)
            # The map's positions: the same average without the filled points (same C, N).
            map_state, X_map = without_filler(
                replace(kf.state, X_canon=kf.points(exported=True)), X_kk, C_kk
            )
            update = self.kernels.fusion.update_pointmap
            X_map = np.asarray(update(map_state, X_map, C_kk, self.fusion_cfg).X_canon)
            with self.lock:
                kf.state, kf.X_map = state, X_map
