"""Divergence watch — a run that goes wrong says so, while it runs and in ``summary.json``.

A monocular run has no metric scale, so "wrong" is judged against the run's own recent motion,
never against a number of metres:

* a pose that is not finite, or whose Sim(3) scale is not positive and finite;
* a frame whose camera centre moved more than ``jump_factor`` times the median step of the
  last ``window`` accepted frames (and more than ``min_jump_frac`` of the extent of the
  trajectory so far, and more than ``min_jump_scale_frac`` of the last accepted Sim(3) scale,
  so that a camera starting to move after standing still is no jump: at rest the median step
  and the extent are both near zero, while the scale is the scene's distance for a prior that
  normalises its pointmaps and one unit for a metric one);
* a frame whose Sim(3) scale changed by more than a factor ``max_scale_ratio`` from the
  previous accepted frame.

:class:`DivergenceMonitor` is fed every tracked pose (``check``) and refuses implausible ones;
the frontend then treats the frame as lost (relocalisation follows), and the monitor keeps a
record of every refusal (``events``). After every backend step it watches the current map's
keyframes for a map that spreads without bound while each step looks plausible (``check_map``,
:func:`find_spread`: a steady Sim(3) scale drift that the keyframes' motion does not explain,
or keyframe spacing grown far beyond the map's first). How severe that is
(:meth:`DivergenceMonitor.severity`) depends on what the watch read: a prior that normalises
its pointmaps gives a world scale that also moves with the scene's distance, so a drift there
is a ``"caution"`` (an event and a sentence in the summary's ``cautions``; the run may still be
plausible) up to ``max_confounded_drift`` and a ``"runaway"`` beyond (an event and a warning:
``plausible`` is false); keyframe spacing that runs away, and a drift of a metric prior's
Sim(3) scales, are always runaways. Each severity is reported once per map.
:func:`guard_backend` undoes a global solve that does
not lower its cost or moves a keyframe too far, and :func:`trajectory_warnings` checks the
final per-frame trajectory the same way (non-finite, jumps, a spread far beyond the path's
steps), for the summary's ``warnings``; these stateless tests and the thresholds
(:class:`DivergenceConfig`) live in :mod:`mslam.system.divergence_checks` and are re-exported
here. Each event has a ``kind``: ``"pose"`` (a refused frame pose), ``"solve"`` (an undone
solve), ``"spread"``.

Public names, in reading order:
    DivergenceConfig, DivergenceMonitor, guard_backend, find_spread, map_spread,
    trajectory_warnings, divergence_report
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mslam.system.divergence_checks import (
    DivergenceConfig,
    Spread,
    find_spread,
    guard_backend,
    map_spread,
    trajectory_warnings,
)
from mslam_ref.conventions import FloatArray

__all__ = [
    "DivergenceConfig",
    "DivergenceMonitor",
    "Spread",
    "divergence_report",
    "find_spread",
    "guard_backend",
    "map_spread",
    "trajectory_warnings",
]


@dataclass
class DivergenceMonitor:
    """Refuses implausible frame poses (module docstring); keeps a record of each refusal.

    Attributes:
        cfg: thresholds.
        events: one dict per refused frame, undone solve or spread (``frame``, ``kind``,
            ``reason``; a spread also its ``factor``, ``severity`` and the ``largest_factor``
            seen at that severity in its map).
    """

    cfg: DivergenceConfig = field(default_factory=DivergenceConfig)
    events: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._centres: deque = deque(maxlen=self.cfg.window + 1)
        self._lo = np.full(3, np.inf)
        self._hi = np.full(3, -np.inf)
        self._last_scale: float | None = None
        self._spread_reported: set[str] = set()

    def reset(self) -> None:
        """Forget recent motion (after a relocalisation the path restarts elsewhere)."""
        self._centres.clear()
        self._last_scale = None

    def new_map(self) -> None:
        """Forget recent motion and the trajectory's extent (``mslam.system.recovery``); the
        spread watch may fire again, for the new map."""
        self.reset()
        self._lo, self._hi = np.full(3, np.inf), np.full(3, -np.inf)
        self._spread_reported = set()

    def refused_frames(self) -> list[int]:
        """Frame index of every refused frame pose so far, in order."""
        return [int(e["frame"]) for e in self.events if e["kind"] == "pose"]

    def check_map(self, frame: int, T_kf: FloatArray, depth: FloatArray | None = None) -> bool:
        """:func:`find_spread` on the current map's keyframe poses ``T_kf`` (K, 8) and their
        canonical points' median distances ``depth`` (K,; None for a metric prior) after the
        backend step of the keyframe made at ``frame``; records the first spread of each
        severity in each map (:meth:`severity`). Returns whether the map looks bounded."""
        found = find_spread(T_kf, self.cfg, depth)
        if found is None:
            return True
        severity = self.severity(found, confounded=depth is not None)
        if severity not in self._spread_reported:
            self._spread_reported.add(severity)
            self.events.append({"frame": int(frame), "kind": "spread", "reason": found.reason,
                                "factor": float(found.factor), "severity": severity,
                                "largest_factor": float(found.factor)})  # fmt: skip
        else:  # the same severity again in this map: keep the largest factor seen
            e = next(e for e in reversed(self.events) if e.get("severity") == severity)
            e["largest_factor"] = max(e["largest_factor"], float(found.factor))
        return False

    def severity(self, found: Spread, confounded: bool) -> str:
        """``"runaway"`` (a warning: the run is not plausible) or ``"caution"`` (reported, the
        run may still be plausible) for a spread :func:`find_spread` found. A world scale read
        with the points' distances (``confounded``: a prior that normalises its pointmaps)
        also moves with the scene's distance, so its drift is a runaway only beyond
        ``max_confounded_drift``; keyframe spacing grown far beyond the map's first, and a
        drift of the Sim(3) scales alone (a metric prior), always are."""
        if found.kind != "drift" or not confounded:
            return "runaway"
        return "runaway" if found.factor > self.cfg.max_confounded_drift else "caution"

    def reason(self, T_WC: FloatArray) -> str | None:
        """Why pose ``T_WC`` (8,) is implausible given recent motion, or None if it is not."""
        T = np.asarray(T_WC, dtype=np.float64)
        if T.shape != (8,) or not np.all(np.isfinite(T)):
            return "non-finite pose"
        s = float(T[7])
        if not s > 0:
            return f"non-positive scale {s:.3g}"
        if self._last_scale is not None:
            ratio = max(s / self._last_scale, self._last_scale / s)
            if ratio > self.cfg.max_scale_ratio:
                return f"scale changed by a factor {ratio:.3g} in one frame"
        if len(self._centres) >= 3:
            c = np.asarray(self._centres)
            steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
            step = float(np.linalg.norm(T[:3] - c[-1]))
            extent = float(np.linalg.norm(self._hi - self._lo))
            limit = max(
                self.cfg.jump_factor * float(np.median(steps)),
                self.cfg.min_jump_frac * extent,
                self.cfg.min_jump_scale_frac * (self._last_scale or 0.0),
            )
            if step > limit and step > 0:
                return f"camera moved {step:.3g} in one frame (recent median step {np.median(steps):.3g})"
        return None

    def check(self, frame: int, T_WC: FloatArray) -> bool:
        """Accept (True, and remember) or refuse (False, and record an event) a frame pose."""
        why = self.reason(T_WC)
        if why is not None:
            self.events.append({"frame": int(frame), "kind": "pose", "reason": why})
            return False
        T = np.asarray(T_WC, dtype=np.float64)
        self._centres.append(T[:3].copy())
        self._lo, self._hi = np.minimum(self._lo, T[:3]), np.maximum(self._hi, T[:3])
        self._last_scale = float(T[7])
        return True

    def warnings(self) -> list[str]:
        """One sentence per kind of event (at least ``warn_refusals`` refused frame poses;
        any undone solve that is not ``minor``), or none."""
        out = []
        frames = [e for e in self.events if e["kind"] == "pose"]
        solves = [e for e in self.events if e["kind"] == "solve" and not e.get("minor")]
        runaways = [e for e in self.events if e["kind"] == "spread" and e["severity"] == "runaway"]
        if len(frames) >= self.cfg.warn_refusals:
            out.append(
                f"{len(frames)} implausible frame pose(s) refused while running (first at "
                f"frame {frames[0]['frame']}: {frames[0]['reason']}); tracking restarted "
                "from relocalisation"
            )
        if solves:
            out.append(f"{len(solves)} global solve(s) undone (first: {solves[0]['reason']})")
        out += [
            f"the map runs away (at frame {e['frame']}): {e['reason']}; the map's scale "
            "after it is not trustworthy, nor are positions that depend on it"
            for e in runaways
        ]
        return out

    def cautions(self) -> list[str]:
        """One sentence per spread of severity ``"caution"`` (:meth:`severity`): worth knowing,
        not a reason to distrust the trajectory."""
        return [
            f"the map's scale moved (at frame {e['frame']}): {e['reason']}; the dense map's "
            "scale after it may be uneven, and so may positions that depend on it. A scene "
            "seen from much nearer or farther (turning towards other surfaces, moving "
            "sideways towards them) looks the same, so this alone does not make the run "
            "implausible"
            for e in self.events
            if e["kind"] == "spread" and e["severity"] == "caution"
        ]


def divergence_report(
    monitor: DivergenceMonitor,
    loop_checks: list[dict[str, Any]],
    T_WC: FloatArray,
    warnings: list[str],
    idx: FloatArray | None = None,
    maps: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The summary's divergence fields: ``warnings`` (the given ones plus the monitor's and
    :func:`trajectory_warnings`' of the final frame poses), ``plausible`` (no warning),
    ``cautions`` (the monitor's, which leave ``plausible`` alone) and ``divergence_events``
    (the monitor's refusals, undone solves and spreads), and the loop-closure
    verdicts of ``mslam.system.loop_verify`` (``loop_closure_checks``, refusals counted).

    Args:
        monitor: the run's monitor (refusals and undone solves in ``events``).
        loop_checks: the loop-closure verdicts (``Backend.loop_checks``).
        T_WC: (M, 8) the final per-frame poses.
        warnings: the warnings found so far (``mslam.system.health.health_report``).
        idx: (M,) the frames of ``T_WC`` (orientation jumps are tested with them).
        maps: ``mslam.system.recovery.Recovery.report``'s answer; the first frames of the maps
            it lists as merged are ``joined`` for :func:`trajectory_warnings`.
    """
    merged = [m for m in (maps or {}).get("maps", []) if m.get("merged") is not None]
    joined = [int(m["first_frame"]) for m in merged]
    out = [*warnings, *monitor.warnings(), *trajectory_warnings(T_WC, idx=idx, joined=joined)]
    return {
        "warnings": out,
        "plausible": not out,
        "cautions": monitor.cautions(),
        "divergence_events": list(monitor.events),
        "loop_closure_candidates_unverified": sum(not c["accepted"] for c in loop_checks),
        "loop_closure_checks": loop_checks,
    }
