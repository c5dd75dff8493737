"""Paper §3.3–3.4 (docs/upstream.md §1.4) — the frontend's steps for priors that need parallax.

The two-view prior (``mslam.priors.twoview``) has no depth from one image, so the frontend
(:class:`~mslam.system.frontend.SlamSystem`, which inherits :class:`ParallaxSteps`) must treat
pairs without parallax apart:

* INIT waits for a first pair with parallax (:meth:`ParallaxSteps.init_with_parallax`), or
  starts without depth under pure rotation (:mod:`mslam.system.rotation_start`);
* a pair is *without parallax* when the prior says so (``last_status == "parallax"``) or when
  its median triangulation angle θ (``last_info["angle_deg"]``), as pixels of parallax
  ``f · θ`` through the focal length of the pair's pointmap (:func:`parallax_px`), is below
  ``tracking.min_pair_parallax_px`` (0.29 px by default, about twice the median error of DIS
  flow; 0.12° at 160x120 with the 60° guess, 0.03° at 640x480). Flow errors are a number of
  pixels at any image size, so a cut-off in pixels means the same at every resolution, where
  one in degrees would be a fraction of a pixel at one size and several pixels at another.
  The depths of such a pair are noise, and so are its pointmaps' rays when the translation is;
* such a frame is tracked against the keyframe before the last one when that pair has
  parallax (never becoming a keyframe), else posed by rotation alone
  (:meth:`ParallaxSteps.track_rotation_only`: the prior's rotation, or the rotation of a
  tracking solve that fuses nothing);
* a rotation-only frame never asks for a keyframe: the new-keyframe test reads the pair's
  matches, which a pair without parallax does not give. Overlap is lost when the prior can no
  longer match the frame to the keyframe (``last_status == "few_inliers"``); the last frame
  tracked or posed by rotation then becomes the keyframe
  (:meth:`ParallaxSteps.promote_last_tracked`). Under a pure rotation this makes a keyframe per
  loss of overlap, not per frame (``synthetic:rotation:60``: numbers in docs/reliability.md);
* a frame posed by rotation alone has no depth of its own (its pair's depths are noise): when
  it becomes a keyframe, its pointmap is its keyframe's, seen through its rays from the same
  centre (:func:`rotated_pointmap`). A keyframe that kept the pair's noise depths spoils the
  edges and relocalisations against it (``synthetic:rotation:60`` at 128x96, 2026-11-26:
  the backend's solve diverged at frame 34; with tracking's ``C_conf`` at 0 the frames after
  the relocalisation at frame 41 were 23-29° off their true orientation; with the rotated
  pointmap the run relocalises at frame 40, 0.7° further off than the last frame before the
  loss, and the frames after it are 2-10° off, as before the loss).
* a relocalised keyframe has no depth of its own either (the prior's ``mono`` of a frame it
  never paired is a plane with ``C = NO_INFO_C``, which the backend's ``C_conf`` masks): it
  takes depth and pose from its pair with the accepted candidate
  (:meth:`ParallaxSteps.place_relocalised`).

Public names, in reading order:
    prior_status, parallax_px, rotation_pose, rotated_pointmap, KeyframePair, TrackedFrame,
    replace_pointmap, ParallaxSteps
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from mslam.config import SlamConfig
from mslam.datasets.frame import Frame
from mslam.priors.base import NO_INFO_C, PairPrediction, Prior
from mslam.system.global_opt import Backend
from mslam.system.keyframes import Keyframe
from mslam.system.map_scale import pinhole_fit
from mslam.system.state import FramePose, FrameStatus, Mode, RunStats
from mslam.system.tracker import Tracker
from mslam_ref import fusion, sim3, so3
from mslam_ref.conventions import FloatArray

__all__ = [
    "KeyframePair",
    "ParallaxSteps",
    "TrackedFrame",
    "parallax_px",
    "prior_status",
    "replace_pointmap",
    "rotated_pointmap",
    "rotation_pose",
]

#: Default of ``tracking.min_pair_parallax_px`` (module docstring): about twice the median
#: error of DIS flow on textured images (~0.15 px, docs/priors.md).
MIN_PAIR_PARALLAX_PX = 0.29


def prior_status(prior: Prior) -> str:
    """The prior's verdict on its last ``pair`` ("ok" for priors that report none)."""
    return str(getattr(prior, "last_status", "ok"))


@dataclass(frozen=True)
class KeyframePair:
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
class TrackedFrame:
    """The last tracked frame, kept in case it must become a keyframe late.

    ``rotated_from``: the keyframe the frame was posed against by rotation alone, else None;
    ``R_kf``: (3, 3) that rotation, frame to keyframe (``T_CkCf = (0, R_kf, 1)``).
    """

    frame: Frame
    T_WC: FloatArray
    p: PairPrediction
    rotated_from: int | None = None
    R_kf: FloatArray | None = None


def parallax_px(angle_deg: float, X: FloatArray, focal_px: float | None = None) -> float:
    """A triangulation angle as pixels of parallax: ``f · θ`` (θ in radians), with ``f`` the
    focal length the prior reports (``focal_px``), else the mean focal length of the pinhole
    fitted to the pair's pointmap ``X`` (H, W, 3) (:func:`mslam.system.map_scale.pinhole_fit`).

    The same angle is a fraction of a pixel in a small image and several pixels in a large
    one; optical flow resolves a fixed number of pixels at any size.
    """
    if focal_px is None:
        fx, fy, _, _ = pinhole_fit(X)
        focal_px = 0.5 * (abs(fx) + abs(fy))
    return float(focal_px) * float(np.radians(angle_deg))


def rotation_pose(q: FloatArray) -> FloatArray:
    """(8,) Sim(3) ``(0, q, 1)`` of a camera turned by unit quaternion ``q`` (4,) about the
    centre it is posed against: no translation, unit scale."""
    return np.concatenate([np.zeros(3), np.asarray(q, np.float64), [1.0]])


def rotated_pointmap(
    X_k: FloatArray, C_k: FloatArray, R_kf: FloatArray, X_f: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The pointmap of a frame whose camera centre is its keyframe's: the keyframe's points,
    seen through the frame's rays.

    A pair without parallax gives the frame no depth of its own. With a shared centre and
    ``X_k = R_kf X_f``, the point on the frame's ray ``r(u)`` is the keyframe's point at the
    pixel where ``R_kf r(u)`` meets the keyframe's image (nearest pixel, through
    :func:`mslam.system.map_scale.pinhole_fit` of ``X_k``): ``X(u) = R_kfᵀ X_k(π(R_kf r(u)))``, with the keyframe's confidence. A ray
    that leaves the keyframe's image gets the median distance of ``X_k`` and ``NO_INFO_C``.

    Args:
        X_k: (H, W, 3) the keyframe's pointmap in its camera; C_k: (H, W) its confidence.
        R_kf: (3, 3) the frame-to-keyframe rotation.
        X_f: (H, W, 3) a pointmap of the frame; only its rays ``X_f / ‖X_f‖`` are used.

    Returns:
        X (H, W, 3) in the frame's camera, C (H, W).
    """
    H, W = X_k.shape[:2]
    fx, fy, cx, cy = pinhole_fit(X_k)
    r = X_f / np.maximum(np.linalg.norm(X_f, axis=-1, keepdims=True), 1e-300)
    d = r @ R_kf.T  # R_kf r, row-wise
    front = d[..., 2] > 1e-12
    dz = np.where(front, d[..., 2], 1.0)
    u = np.rint(fx * d[..., 0] / dz + cx)
    v = np.rint(fy * d[..., 1] / dz + cy)
    inside = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    ui = np.where(inside, u, 0).astype(np.int64)
    vi = np.where(inside, v, 0).astype(np.int64)
    dist = float(np.median(np.linalg.norm(X_k, axis=-1)))
    X = np.where(inside[..., None], X_k[vi, ui] @ R_kf, r * dist)
    C = np.where(inside, C_k[vi, ui], NO_INFO_C)
    return X, C


def replace_pointmap(
    backend: Backend, kf: Keyframe, X: FloatArray, C: FloatArray, T_WC: FloatArray | None = None
) -> None:
    """Give keyframe ``kf`` a new canonical pointmap ``X`` (H, W, 3) with confidence ``C``
    (H, W), and the map's copy of it, and with ``T_WC`` (8,) a new pose (also its initial
    one), under the backend's lock."""
    state = fusion.init_pointmap(X.reshape(-1, 3), C.reshape(-1), backend.fusion_cfg)
    with backend.lock:
        kf.state, kf.X_map = state, np.asarray(state.X_canon, np.float64).copy()
        if T_WC is not None:
            kf.T_WC, kf.T_WC_init = np.asarray(T_WC, np.float64), np.asarray(T_WC, np.float64)


class ParallaxSteps:
    """The steps of :class:`~mslam.system.frontend.SlamSystem` for priors that need parallax
    (module docstring); a mixin that only ``SlamSystem`` inherits, which owns these fields."""

    cfg: SlamConfig
    prior: Prior
    stats: RunStats
    backend: Backend
    tracker: Tracker
    mode: Mode
    anchor: FloatArray
    T_WC_last: FloatArray
    poses: list[FramePose]
    init_candidate: Frame | None
    init_pending: list[Frame]
    init_rotations: dict[int, FloatArray]
    init_rotated_pair: PairPrediction | None
    last_tracked: TrackedFrame | None
    record: Callable[..., None]
    track: Callable[..., FrameStatus]
    make_keyframe: Callable[..., int]
    lose_tracking: Callable[[], None]
    start_by_rotation: Callable[[Frame | None], FrameStatus | None]
    lose_waiting: Callable[[], None]

    def pair_status(self, p: PairPrediction) -> str:
        """The prior's verdict on its last pair ``p``, ``"parallax"`` also for an ``"ok"`` pair
        whose median parallax (:func:`parallax_px`) is below ``tracking.min_pair_parallax_px``."""
        status = prior_status(self.prior)
        info = getattr(self.prior, "last_info", None)
        if status == "ok" and isinstance(info, dict) and "angle_deg" in info:
            section = dict(self.cfg.sections.get("tracking", {}))
            limit = float(section.get("min_pair_parallax_px", MIN_PAIR_PARALLAX_PX))
            focal = info.get("focal_px")
            angle = float(info["angle_deg"])
            X = np.asarray(p.X_ii, np.float64)
            if parallax_px(angle, X, None if focal is None else float(focal)) < limit:
                return "parallax"
        return status

    def init_with_parallax(self, frame: Frame) -> FrameStatus:
        """INIT for priors without single-image depth: wait for a non-degenerate first pair.

        The first frame is the candidate; later frames wait in ``init_pending``. At the first
        frame whose pairs with the candidate are usable in both directions, the candidate
        becomes keyframe 0 (``X_ii`` of ``pair(candidate, frame)``), the frame is tracked and
        made keyframe 1, and the waiting frames are tracked against these two keyframes.
        """
        cand = self.init_candidate
        if cand is None:
            self.restart_wait(frame)
            return FrameStatus.WAITING
        with self.stats.timer("prior"):
            p_fc = self.prior.pair(frame, cand)  # the direction tracking uses must be usable too
            status = prior_status(self.prior)
            R_fc = getattr(self.prior, "last_R_ji", None) if status == "parallax" else None
            p = self.prior.pair(cand, frame) if status == "ok" else None
        if p is not None:
            status = prior_status(self.prior)
        if p is None or status != "ok":
            if status == "few_inliers":  # too far apart to match
                started = self.start_by_rotation(frame)  # the waiting frames turned: start
                if started is not None:
                    return started
                self.lose_waiting()  # else start again from here
                self.restart_wait(frame)
            else:
                self.init_pending.append(frame)
                if R_fc is not None:  # turned from the candidate (module rotation_start)
                    self.init_rotations[int(frame.index)] = np.asarray(R_fc)
                    self.init_rotated_pair = p_fc  # the latest only: a pair is megabytes
            return FrameStatus.WAITING
        k = self.backend.add_keyframe(cand, self.anchor, p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
        self.backend.retrieval.update(self.backend.keyframes[k].retrieval_features())
        self.T_WC_last = self.backend.keyframes[k].T_WC.copy()
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
        self.restart_wait(None)
        return result

    def restart_wait(self, candidate: Frame | None) -> None:
        """Start INIT's wait for parallax afresh from ``candidate`` (None: from the next frame):
        no waiting frames, no rotations kept (``mslam.system.rotation_start``)."""
        self.init_candidate, self.init_pending = candidate, []
        self.init_rotations, self.init_rotated_pair = {}, None

    def keyframe_pair(self, frame: Frame) -> KeyframePair:
        """The pair with the last keyframe, or with the one before it when the prior flags the
        first pair degenerate (``last_status``); with the rotation to pose the frame by when
        the pair with the last keyframe lacks parallax and no fallback worked."""
        kf_idx = len(self.backend.keyframes) - 1
        with self.stats.timer("prior"):
            p = self.prior.pair(frame, self.backend.keyframes[kf_idx].frame)
        status = self.pair_status(p)
        if status in ("ok", "same"):
            return KeyframePair(kf_idx, p, False, status, None)
        R_ji = getattr(self.prior, "last_R_ji", None) if status == "parallax" else None
        if kf_idx > self.backend.map_start:  # the keyframe before it, in the same map
            with self.stats.timer("prior"):
                p_prev = self.prior.pair(frame, self.backend.keyframes[kf_idx - 1].frame)
            if self.pair_status(p_prev) == "ok":
                return KeyframePair(kf_idx - 1, p_prev, True, status, None)
        return KeyframePair(kf_idx, p, False, status, R_ji)

    def track_rotation_only(self, frame: Frame, pair: KeyframePair) -> FrameStatus | None:
        """Pose a frame without parallax to its keyframe: a rotation, no translation.

        Without parallax the camera centre is within a small fraction of the scene depth from
        the keyframe's, so ``T_CkCf = (0, R_ji, 1)`` is off by at most that baseline. ``R_ji``
        is the prior's (``pair.R_ji``) or, when the prior gives none, the rotation of a
        tracking solve on the pair that fuses nothing (None, nothing recorded, if it fails).
        Nothing is fused and the frame never asks for a keyframe; it may become one late
        (:meth:`promote_last_tracked`).
        """
        kf = self.backend.keyframes[pair.kf_idx]
        q = None if pair.R_ji is None else so3.from_matrix(pair.R_ji)
        if q is None:
            res = self.tracker.track(kf, pair.p, self.T_WC_last, fuse=False)
            if res is None:
                return None
            q = np.asarray(res.T_CkCf[3:7], np.float64)
        T_CkCf = rotation_pose(q)
        self.T_WC_last = sim3.mul(kf.T_WC, T_CkCf)
        self.last_tracked = TrackedFrame(
            frame, self.T_WC_last, pair.p, pair.kf_idx, so3.to_matrix(q)
        )
        self.record(frame, pair.kf_idx, T_CkCf, FrameStatus.ROTATION)
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
        if last is None or last.frame.index == self.backend.keyframes.last().frame.index:
            return False
        self.poses = [q for q in self.poses if q.index != last.frame.index]
        p = last.p
        if last.rotated_from is not None and last.R_kf is not None:
            kf = self.backend.keyframes[last.rotated_from]  # no depth of its own: kf's, rotated
            X, C = rotated_pointmap(
                kf.state.X_canon.reshape(*kf.shape, 3),
                fusion.average_confidence(kf.state).reshape(kf.shape),
                last.R_kf,
                np.asarray(p.X_ii, np.float64),
            )
            p = replace(p, X_ii=X, C_ii=C)
        self.make_keyframe(last.frame, last.T_WC, p)
        return True

    def place_relocalised(self, n: int, best: int) -> None:
        """Give relocalised keyframe ``n`` depth and a pose from its pair with the accepted
        candidate ``best`` (``mslam.system.reloc``), for a prior without single-image depth.

        Such a prior's ``mono`` of a frame it has never paired is a fronto-parallel plane with
        ``C = NO_INFO_C``: the backend's ``C_conf`` masks every residual of the keyframe, so
        the solve cannot move it from the candidate's pose it was given. Instead, as when
        tracking, the pair ``prior.pair(frame of n, frame of best)`` places it: with parallax,
        its own pointmap ``X_ii`` and a tracking solve against ``best`` that fuses nothing;
        without, ``best``'s points seen through its rays (:func:`rotated_pointmap`) and the
        pair's rotation. A pair that gives neither leaves the keyframe as it is.
        """
        if not getattr(self.prior, "needs_parallax", False):
            return
        kf, ref = self.backend.keyframes[n], self.backend.keyframes[best]
        with self.stats.timer("prior"):
            p = self.prior.pair(kf.frame, ref.frame)
        status = self.pair_status(p)
        R = getattr(self.prior, "last_R_ji", None) if status == "parallax" else None
        if status not in ("ok", "parallax"):
            return
        # The rotation of the pair (parallax without a pose), else that of a tracking solve.
        if R is not None:
            res = None
            q = so3.from_matrix(R)
        else:
            res = self.tracker.track(ref, p, ref.T_WC, fuse=False)
            self.tracker.idx_f2k = None
            if res is None:
                return
            q = np.asarray(res.T_CkCf[3:7], np.float64)
        if status == "ok" and res is not None:
            X, C, T_WC = np.asarray(p.X_ii, np.float64), np.asarray(p.C_ii), res.T_WC
        else:
            X, C = rotated_pointmap(
                ref.state.X_canon.reshape(*ref.shape, 3),
                fusion.average_confidence(ref.state).reshape(ref.shape),
                so3.to_matrix(q),
                np.asarray(p.X_ii, np.float64),
            )
            T_WC = sim3.mul(ref.T_WC, rotation_pose(q))
        replace_pointmap(self.backend, kf, X, C, T_WC)
