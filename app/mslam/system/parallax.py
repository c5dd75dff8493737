"""The frontend's handling of priors that need parallax (the classical two-view prior).

A prior that declares ``needs_parallax`` or reports ``last_status`` (``mslam.priors.twoview``)
cannot make a pointmap from two images seen from one place. The frontend then:

* at the start, waits for a frame with enough parallax to the first one before fixing the first
  two keyframes, and poses the frames that waited (:func:`init_with_parallax`);
* when the pair with the last keyframe is degenerate, tracks against the keyframe before it
  (:func:`keyframe_pair`), or poses the frame by the pair's rotation alone
  (:func:`track_rotation_only`);
* when the frame is too far from the last keyframe, makes the last tracked frame a keyframe
  first (:func:`promote_last_tracked`).

Other priors never reach these functions. ``system`` is the ``mslam.system.frontend.SlamSystem``.

Public names, in reading order:
    init_with_parallax, keyframe_pair, track_rotation_only, promote_last_tracked
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam.datasets.frame import Frame
from mslam.system.state import Mode
from mslam_ref import sim3, so3

__all__ = ["init_with_parallax", "keyframe_pair", "promote_last_tracked", "track_rotation_only"]


def init_with_parallax(system: Any, frame: Frame) -> str:
    """INIT for priors without single-image depth: wait for a non-degenerate first pair.

    The first frame is the candidate; later frames wait in ``_init_pending``. At the first
    frame whose pairs with the candidate are usable in both directions, the candidate
    becomes keyframe 0 (``X_ii`` of ``pair(candidate, frame)``), the frame is tracked and
    made keyframe 1, and the waiting frames are tracked against these two keyframes.
    """
    cand = system._init_candidate
    if cand is None:
        system._init_candidate, system._init_pending = frame, []
        return "waiting"
    with system.timer("prior"):
        system.prior.pair(frame, cand)  # the direction tracking uses must be usable too
        status = getattr(system.prior, "last_status", "ok")
        p = system.prior.pair(cand, frame) if status == "ok" else None
    if status == "ok":
        status = getattr(system.prior, "last_status", "ok")
    if status != "ok":
        if status == "few_inliers":  # too far apart to match: start again from here
            for f in [cand, *system._init_pending]:
                system._lost(f)
            system._init_candidate, system._init_pending = frame, []
        else:
            system._init_pending.append(frame)
        return "waiting"
    k = system.new_keyframe(cand, sim3.identity(), p.X_ii, p.C_ii, p.D_ii, p.Q_ii)
    system.retrieval.update(system.keyframes[k].features)
    system.T_WC_last = system.keyframes[k].T_WC.copy()
    system._record(cand, k, None, "keyframe")
    system.mode = Mode.TRACKING
    status = system.track(frame, force_keyframe=True)
    if status == "lost":
        system.stats.tracking_failures += 1
        system.stats.lost_frames += 1
        system.mode = Mode.RELOC
    else:
        T_last = system.T_WC_last.copy()
        for f in system._init_pending:
            if system.track(f, allow_keyframe=False) == "lost":
                system.stats.lost_frames += 1
        system.T_WC_last, system.idx_f2k = T_last, None
    system._init_candidate, system._init_pending = None, []
    return status


def keyframe_pair(system: Any, frame: Frame) -> tuple[int, Any, bool]:
    """``(kf_idx, prediction, fallback)``: the pair with the last keyframe, or with the one
    before it when the prior flags the first pair degenerate (``last_status``).

    Sets ``_rotation_only`` to the prior's ``last_R_ji`` when the pair with the last
    keyframe lacks parallax and no fallback worked (else None).
    """
    system._rotation_only = None
    kf_idx = len(system.keyframes) - 1
    with system.timer("prior"):
        p = system.prior.pair(frame, system.keyframes[kf_idx].frame)
    status = getattr(system.prior, "last_status", "ok")
    system._first_status = status
    if status in ("ok", "same"):
        return kf_idx, p, False
    R_ji = getattr(system.prior, "last_R_ji", None) if status == "parallax" else None
    if kf_idx > 0:
        with system.timer("prior"):
            p_prev = system.prior.pair(frame, system.keyframes[kf_idx - 1].frame)
        if system.prior.last_status == "ok":
            return kf_idx - 1, p_prev, True
    system._rotation_only = R_ji
    return kf_idx, p, False


def track_rotation_only(system: Any, frame: Frame, kf_idx: int) -> str:
    """Pose a frame without parallax to its keyframe: the pair's rotation, no translation.

    With parallax below the prior's threshold the camera centre is within a small fraction
    of the scene depth from the keyframe's, so ``T_CkCf = (0, R_ji, 1)`` is off by at most
    that baseline. Nothing is fused and the frame never becomes a keyframe.
    """

    T_CkCf = np.concatenate([np.zeros(3), so3.from_matrix(system._rotation_only), [1.0]])
    system.T_WC_last = sim3.mul(system.keyframes[kf_idx].T_WC, T_CkCf)
    system._record(frame, kf_idx, T_CkCf, "rotation")
    return "rotation"


def promote_last_tracked(system: Any) -> bool:
    """Make the last tracked frame a keyframe (late), when the current frame is already
    too far from the last keyframe for the prior (``last_status == "few_inliers"``).

    A prior whose correspondences break down under large motion (the two-view prior's
    optical flow) can lose a keyframe before the match-fraction test asks for a new one;
    the previous frame, tracked with its own pointmap ``X_ii`` and pose, is then the
    keyframe that should have been made. Returns whether one was added.
    """
    last = system._last_tracked
    system._last_tracked = None
    if last is None or last[0].index == system.keyframes[len(system.keyframes) - 1].frame.index:
        return False
    frame, T_WC, X, C, D, Q = last
    k = system.new_keyframe(frame, T_WC, X, C, D, Q)
    system.poses = [q for q in system.poses if q.index != frame.index]
    system._record(frame, k, None, "keyframe")
    system.keyframe_added(k)
    system.idx_f2k = None
    return True
