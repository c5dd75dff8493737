"""The divergence watch's tests of pose arrays, and their thresholds (``DivergenceConfig``).

Stateless checks on arrays of Sim(3) poses, judged against the run's own motion (a monocular
run has no metric scale), for :class:`mslam.system.divergence.DivergenceMonitor` and the
summary:

* :func:`guard_backend` decides whether a global solve is kept: a solve whose result is not
  finite, whose final cost exceeds its first, or that moves a keyframe by more than
  ``max_backend_move`` times the keyframes' median spacing, is undone.
* :func:`map_spread` watches one map's keyframes for a map that spreads without bound while
  each step looks plausible (a slow runaway): the scene's distance in world units (each
  keyframe's Sim(3) scale times its canonical points' median distance) moving steadily one
  way over the last ``spread_window`` keyframes (net log change at least ``min_drift_trend``
  of the summed absolute log changes) by a factor beyond ``max_scale_drift``, or by a factor
  beyond ``max_uneven_drift`` however unevenly, once the part that the keyframes' motion along
  their optical axes explains is taken out (a prior that normalises its pointmaps, as MASt3R
  and the two-view prior do, shrinks the scale of a camera walking towards a wall: the scene's
  distance falls by the distance walked), or the recent keyframe spacing grown beyond
  ``max_spacing_growth`` times the map's first spacings.
* :func:`trajectory_warnings` checks the final per-frame trajectory (non-finite poses, jumps
  far beyond its median step, a spread of Sim(3) scales far beyond its path, orientation jumps
  through :func:`mslam.system.turns.turn_warnings`), for the summary's ``warnings``.

Public names, in reading order:
    DivergenceConfig, guard_backend, explained_log_changes, Spread, find_spread, map_spread,
    trajectory_warnings
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mslam.system.turns import TurnConfig, turn_warnings
from mslam_ref import so3
from mslam_ref.conventions import FloatArray

__all__ = [
    "DivergenceConfig",
    "Spread",
    "explained_log_changes",
    "find_spread",
    "guard_backend",
    "map_spread",
    "trajectory_warnings",
]

#: In the final trajectory's first quarter, a step below this share of the quarter's 90th
#: percentile step is a camera at rest, not the motion a jump is measured against (a clip with
#: 20 frames at rest first: rest steps 0.3 mm, moving steps 6 mm, 2026-11-26).
REST_STEP_FRAC = 0.05

#: A camera that moves past the scene it looked at keeps at least this share of its distance
#: in :func:`map_spread`'s motion model (a bound on the explained scale change per keyframe).
MIN_DEPTH_FRAC = 0.1


@dataclass(frozen=True)
class DivergenceConfig:
    """Thresholds of the divergence watch (module docstring).

    Attributes:
        window: accepted frames whose steps give the "recent motion".
        jump_factor: a step longer than this many recent median steps is a jump.
        min_jump_frac: ... and longer than this share of the trajectory's extent so far.
        max_scale_ratio: a frame-to-frame Sim(3) scale change beyond this factor is refused
            (loose: with the two-view prior each pair has its own normalisation, and factors
            up to ~10 between consecutive frames were seen on well-tracked 7-Scenes frames).
        max_final_jump: in the final trajectory, a step longer than this many median steps
            is reported.
        max_backend_move: a global solve that moves a keyframe by more than this many median
            keyframe spacings is undone.
        max_final_scale_ratio: in the final trajectory, a spread of the frames' Sim(3) scales
            beyond this factor is reported.
        warn_refusals: refused frames that make a warning (fewer are listed in the events
            only: a single refused frame followed by a relocalisation is a recovered run).
        spread_window: consecutive keyframes whose scale changes :func:`map_spread` reads.
        max_scale_drift: their scale moving by more than this factor in all, ...
        min_drift_trend: ... with the net change at least this share of the summed absolute
            changes (1: every step the same way), is a drift.
        max_uneven_drift: their scale moving by more than this factor in all is a drift however
            unevenly it moved. Largest net change not explained by the motion, over every
            check of a run (RGB-only, 7-Scenes clip, 2026-11-27): on runs with ATE at most
            4.8 cm, a factor 8.1 (phone-like variant; JPEG 3.9, exposure 2.6, forward 1.2, the
            900-frame loop 1.3); under Gaussian noise of 30 grey levels per pixel at the
            160x120 working resolution (ATE 12.8 cm), 126 with 72 % of the total change net,
            which the steady test passes. 25 sits a factor 3 above the first and 5 below the
            second.
        max_confounded_drift: a drift of the world scale read with the keyframes' point
            distances (a prior that normalises its pointmaps) is a runaway beyond this factor
            and a caution up to it. That reading also moves when the camera turns towards
            farther surfaces or sinks towards the floor, so a factor of a few does not tell
            drift from scene: on sound real videos it reached 2.1 (TUM fr1_rpy turning, ATE
            1.7 % of the path) and 7.4 (a drone landing, 2.3 %); maps that went wrong reached
            17 (calibrated KITTI excerpts shrinking, ATE 7.5 and 11.3 m before the depth
            weight) and 126-761 (noisy and dark variants of the 7-Scenes clip before the
            distance weight) (2026-11-27/29, benchmarks/RESULTS.md "Cautions and runaways").
            A reading of the Sim(3) scales alone (a metric prior) has no such confound: every
            drift there is a runaway.
        max_spacing_growth: recent median keyframe spacing beyond this many times the map's
            first median spacing is a spreading map.
        min_jump_scale_frac: a step shorter than this share of the Sim(3) scale (the last
            accepted frame's; in the final trajectory, the smaller of its two frames') is
            never a jump.
        turn: the orientation-jump thresholds (:class:`mslam.system.turns.TurnConfig`).
        warn_cost_rise: an undone solve whose only fault is a cost rise below this share is
            minor: kept in the events, not warned about. Gauss–Newton on robustly reweighted
            residuals is not monotone by fractions of a percent (0.15 % measured on a
            597-frame calibrated run, 2026-11-26); a diverging solve raises the cost manyfold.
    """

    window: int = 20
    jump_factor: float = 25.0
    min_jump_frac: float = 0.5
    max_scale_ratio: float = 100.0
    max_final_jump: float = 50.0
    max_backend_move: float = 20.0
    max_final_scale_ratio: float = 1e3
    warn_refusals: int = 3
    spread_window: int = 8
    max_scale_drift: float = 2.0
    min_drift_trend: float = 0.8
    max_uneven_drift: float = 25.0
    max_confounded_drift: float = 10.0
    max_spacing_growth: float = 25.0
    min_jump_scale_frac: float = 0.05
    turn: TurnConfig = field(default_factory=TurnConfig)
    warn_cost_rise: float = 0.05


def _median_spacing(P: FloatArray) -> float:
    if len(P) < 2:
        return 0.0
    return float(np.median(np.linalg.norm(np.diff(P, axis=0), axis=1)))


def guard_backend(
    T_old: FloatArray,
    T_new: FloatArray,
    costs: tuple[float, ...],
    cfg: DivergenceConfig,
    cost_rise: float = 1e-6,
) -> str | None:
    """Why a global solve must be undone, or None to keep it.

    Args:
        T_old, T_new: (K, 8) keyframe poses before and after the solve.
        costs: the solve's cost per iteration (before each update), first to last.
        cfg: ``max_backend_move``.
        cost_rise: the relative cost rise tolerated (with ``cfg.warn_cost_rise``: whether an
            undone solve is minor).

    Returns:
        a reason (non-finite result, cost increased, a keyframe moved too far) or None.
    """
    T_old, T_new = np.asarray(T_old, np.float64), np.asarray(T_new, np.float64)
    if not np.all(np.isfinite(T_new)) or not np.all(T_new[:, 7] > 0):
        return "the solve returned non-finite poses or scales"
    if len(costs) >= 2 and np.isfinite(costs[0]) and not costs[-1] <= costs[0] * (1 + cost_rise):
        return f"the solve's cost rose from {costs[0]:.4g} to {costs[-1]:.4g}"
    spacing = _median_spacing(T_old[:, :3])
    if spacing > 0:
        move = float(np.max(np.linalg.norm(T_new[:, :3] - T_old[:, :3], axis=1)))
        if move > cfg.max_backend_move * spacing:
            return f"the solve moved a keyframe by {move / spacing:.3g} keyframe spacings"
    return None


def explained_log_changes(T: FloatArray, depth: FloatArray) -> FloatArray:
    """Per link, the log change of the keyframes' Sim(3) scale that their motion explains.

    The keyframes' scene distance in world units is ``d_k = s_k · depth_k``; moving by
    ``f_k = (c_{k+1} - c_k) · z_k`` along the optical axis ``z_k`` takes the same scene to
    distance ``d_k - f_k`` (exactly for a wall facing the camera). A prior that normalises
    its pointmaps (``depth_k`` constant) then needs ``s_{k+1} / s_k = (d_k - f_k) / d_k``;
    those log ratios are returned, (K-1,).

    Args:
        T: (K, 8) keyframe poses in creation order.
        depth: (K,) median distance of each keyframe's canonical points to its camera.
    """
    z = so3.act(T[:-1, 3:7], np.array([0.0, 0.0, 1.0]))  # (K-1, 3) optical axes in the world
    f = np.sum(np.diff(T[:, :3], axis=0) * z, axis=1)
    d = T[:-1, 7] * depth[:-1]
    return np.log(np.maximum(d - f, MIN_DEPTH_FRAC * d) / d)


@dataclass(frozen=True)
class Spread:
    """What :func:`find_spread` saw in one map's keyframes.

    Attributes:
        reason: one sentence, for the run's summary.
        factor: the net drift factor of the world scale over the window (``x`` or ``1/x``,
            whichever is larger), or the growth of the keyframe spacing.
        kind: ``"drift"`` (the world scale) or ``"spacing"`` (the keyframe spacing).
    """

    reason: str
    factor: float
    kind: str


def map_spread(
    T_kf: FloatArray, cfg: DivergenceConfig = DivergenceConfig(), depth: FloatArray | None = None
) -> str | None:
    """The sentence of :func:`find_spread` (why keyframe poses ``T_kf`` (K, 8) look like a map
    that spreads without bound), or None."""
    found = find_spread(T_kf, cfg, depth)
    return None if found is None else found.reason


def find_spread(
    T_kf: FloatArray, cfg: DivergenceConfig = DivergenceConfig(), depth: FloatArray | None = None
) -> Spread | None:
    """Whether keyframe poses ``T_kf`` (K, 8) of one map, in creation order, look like a map
    that spreads without bound, or None (module docstring: a steady Sim(3) scale drift over the
    last ``spread_window`` keyframes that the keyframes' motion towards or away from the scene
    does not explain, or an uneven one beyond ``max_uneven_drift``, or keyframe spacing grown
    ``max_spacing_growth``-fold).

    ``depth`` (K,): the median distance of each keyframe's canonical points to its camera.
    With it, the watch reads the scene's distance in world units, ``s_k · depth_k``, rather
    than the scale ``s_k`` alone (a keyframe whose canonical points are at another scale than
    its predecessor's, as mono or fused pointmaps are, changes ``s_k`` without changing the
    map), and the part of that change which the camera's motion along its optical axis
    explains (walking towards a wall shrinks a normalised prior's scale) is not drift; without
    it every steady scale change counts."""
    T = np.asarray(T_kf, dtype=np.float64).reshape(-1, 8)
    w = cfg.spread_window
    if len(T) <= w or not np.all(np.isfinite(T)) or not np.all(T[:, 7] > 0):
        return None
    log_d = np.log(T[-w - 1 :, 7])  # the scene's distance in world units, up to the depths
    m = None if depth is None else np.asarray(depth, dtype=np.float64).reshape(-1)[-w - 1 :]
    if m is not None and not (len(m) == w + 1 and np.all(np.isfinite(m)) and np.all(m > 0)):
        m = None
    if m is not None:
        log_d = log_d + np.log(m)  # s_k · depth_k: a pointmap's own scale change is no drift
    d = np.diff(log_d)
    trend = abs(float(d.sum())) / max(float(np.abs(d).sum()), 1e-300)  # 1: every step one way
    net = float(d.sum())
    if m is not None:
        # Motion only explains a change the same way as the observed one, and at most all.
        explained = float(np.sum(explained_log_changes(T[-w - 1 :], m)))
        net -= float(np.clip(explained, min(net, 0), max(net, 0)))
    drift = float(np.exp(abs(net)))
    steady = trend >= cfg.min_drift_trend
    if drift > cfg.max_scale_drift and (steady or drift > cfg.max_uneven_drift):
        way = "grew" if net > 0 else "shrank"
        why = (
            f"the keyframes' world scale {way} by a factor {drift:.3g} over the last {w} "
            f"keyframes (Sim(3) scale times their points' distance, where known), "
            f"{'steadily' if steady else 'unevenly'} (net change "
            f"{100 * trend:.0f} % of the total change), beyond what their motion towards or "
            "away from the scene explains"
        )
        return Spread(why, drift, "drift")
    steps = np.linalg.norm(np.diff(T[:, :3], axis=0), axis=1)
    first, recent = float(np.median(steps[:w])), float(np.median(steps[-w:]))
    if first > 0 and recent > cfg.max_spacing_growth * first:
        why = (
            f"the recent keyframe spacing is {recent / first:.3g} times the map's first "
            "(the map grows far beyond the recent motion)"
        )
        return Spread(why, recent / first, "spacing")
    return None


def trajectory_warnings(
    T_WC: FloatArray,
    cfg: DivergenceConfig = DivergenceConfig(),
    idx: FloatArray | None = None,
    joined: Sequence[int] = (),
) -> list[str]:
    """Warnings about a final per-frame trajectory (M, 8): non-finite poses, jumps far beyond
    its median step, a spread far beyond its path length allows; with the frame indices
    ``idx`` (M,), orientation jumps too (:func:`mslam.system.turns.turn_warnings`).

    ``joined`` lists the frames that started a map later merged into an earlier one
    (``mslam.system.merge``): the step from the last posed frame before such a frame to the
    first after it is the camera's own jump (a cut, or motion lost while unposed), placed by
    the merge's verified connections, so it is not tested as a jump (needs ``idx``)."""
    T = np.asarray(T_WC, dtype=np.float64).reshape(-1, 8)
    if len(T) == 0:
        return []
    finite = np.all(np.isfinite(T), axis=1)
    out = []
    if not finite.all():
        out.append(f"{int((~finite).sum())} frame pose(s) are not finite")
    if idx is not None:
        out += turn_warnings(np.asarray(idx)[finite], T[finite, 3:7], cfg.turn)
    P = T[finite, :3]
    if len(P) < 3:
        return out
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    # The first quarter's median too: a run that diverges for most of its frames has a large
    # overall median step. Its steps at rest (a camera that stood still at the start) are left
    # out, else a later step of ordinary size would be hundreds of "median steps".
    first = steps[: max(1, len(steps) // 4)]
    first = first[first >= REST_STEP_FRAC * np.quantile(first, 0.9)]
    med = min(float(np.median(steps)), float(np.median(first)))
    # A step within a small share of the frame's scale is no jump (a camera that stood still
    # for the first quarter has a median step near zero there).
    sc = np.abs(T[finite, 7])
    big = np.where(steps > cfg.min_jump_scale_frac * np.minimum(sc[:-1], sc[1:]), steps, 0.0)
    f = np.asarray(idx)[finite] if idx is not None else np.arange(len(P))
    for j in joined:  # the step into a merged map's first posed frame
        big[(f[:-1] < j) & (f[1:] >= j)] = 0.0
    if med > 0 and big.max() > cfg.max_final_jump * med:
        k = int(np.argmax(big))
        out.append(
            f"the trajectory jumps {big.max() / med:.3g} median steps between frames "
            f"{int(f[k])} and {int(f[k + 1])}; positions after a jump are not trustworthy"
        )
    s = T[finite, 7]
    if np.all(s > 0) and s.max() / s.min() > cfg.max_final_scale_ratio:
        out.append(
            f"the frames' Sim(3) scale spans a factor {s.max() / s.min():.3g}; the map's scale "
            "drifted or collapsed"
        )
    return out
