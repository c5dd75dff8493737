"""Run health — how much of a run can be trusted: posed fraction, lost spans, plausibility.

A SLAM run can end with a small ATE and still be useless: the ATE only covers the frames that
have a pose, and a Sim(3) alignment hides a collapsed scale. ``mslam run`` therefore reports,
in ``summary.json`` and on the console:

* the fraction of frames with a pose (``frames_posed_fraction``) and the spans of frames seen
  while lost (``lost_spans``: ``[first, last]`` frame indices, inclusive);
* the frames where relocalisation succeeded (``relocalised_at``);
* the frames posed by rotation alone (``frames_posed_by_rotation``: the two-view prior's frames
  without parallax, at their keyframe's centre; all of a pure pan's frames);
* ``warnings``: one sentence per reason to distrust the run, and ``plausible`` (no warning).

A run is flagged when fewer than :data:`MIN_POSED_FRACTION` of its frames have a pose, when
the prior is metric (its pointmaps are in metres: the class says so, ``metric = True``, read by
:func:`mslam.priors.base.is_metric` and kept in ``summary.json`` as ``prior_metric``) but the
aligned Sim(3) scale is
outside ``[1 / MAX_SCALE_FACTOR, MAX_SCALE_FACTOR]`` by more than the path can tell (the scale
error moves positions by more than the ATE), and when ``--skip-bad-frames`` skipped
frames (:func:`skip_warnings`: they are in no count and have no pose).

Public names, in reading order:
    MIN_POSED_FRACTION, MAX_SCALE_FACTOR, lost_spans, relocalised_at,
    health_report, skip_warnings
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "MAX_SCALE_FACTOR",
    "MIN_POSED_FRACTION",
    "health_report",
    "lost_spans",
    "relocalised_at",
    "skip_warnings",
]

#: Below this fraction of frames with a pose a run is flagged as implausible.
MIN_POSED_FRACTION = 0.95

#: With a metric prior, an aligned scale beyond this factor (either way) is flagged.
MAX_SCALE_FACTOR = 1.1


def lost_spans(poses: list[Any]) -> list[list[int]]:
    """``[first, last]`` frame indices of each run of consecutive ``"lost"`` frames.

    Args:
        poses: the system's per-frame records (``FramePose``: ``index``, ``status``), in order.
    """
    spans: list[list[int]] = []
    prev_lost = False
    for p in poses:
        lost = p.status == "lost"
        if lost and prev_lost:
            spans[-1][1] = int(p.index)
        elif lost:
            spans.append([int(p.index), int(p.index)])
        prev_lost = lost
    return spans


def relocalised_at(poses: list[Any]) -> list[int]:
    """Frame indices where relocalisation succeeded."""
    return [int(p.index) for p in poses if p.status == "relocalised"]


def _scale_shows(ate: dict[str, Any], s: float) -> bool:
    """Whether the scale error ``s`` moves the positions by more than the ATE does: at scale 1
    the estimate's positions are off by about ``|1/s - 1|`` times the path's reach
    (``reference_spread``). On a path that barely leaves its centre (a camera turning on the
    spot) a scale of 0.9 changes them less than the noise, and the alignment's scale is not
    determined (TUM fr1_rpy, RGB-D: spread 6.4 cm, ATE 1.77 cm, scale 0.89, and 1.92 cm with
    the scale held at 1; benchmarks/RESULTS.md, "The aligned scale on a path that turns on
    the spot"). Without ``reference_spread`` every scale out of range counts."""
    spread = ate.get("reference_spread")
    if spread is None or ate.get("ate_rmse") is None:
        return True
    return abs(1.0 / s - 1.0) * float(spread) > float(ate["ate_rmse"])


def health_report(
    poses: list[Any],
    frames: int,
    posed: int,
    prior: str | None,
    ate: dict[str, Any] | None,
    *,
    metric: bool,
) -> dict[str, Any]:
    """The trust fields of ``summary.json`` (module docstring).

    Args:
        poses: per-frame records; frames: frames read; posed: frames with a pose;
        prior: the prior's name; ate: ``AteResult.to_dict()`` of the run, or None.
        metric: the prior's pointmaps are in metres (``mslam.priors.base.is_metric``).

    Returns:
        ``frames_posed_fraction``, ``lost_spans``, ``relocalised_at``,
        ``frames_posed_by_rotation``, ``warnings``, ``plausible``.
    """
    frac = posed / frames if frames else 0.0
    warnings = []
    if frac < MIN_POSED_FRACTION:
        warnings.append(
            f"only {posed} of {frames} frames ({100 * frac:.0f}%) have a pose "
            f"(< {100 * MIN_POSED_FRACTION:.0f}%); the ATE covers those frames only"
        )
    if ate is not None and metric:
        s = float(ate.get("scale", 1.0))
        if not (1.0 / MAX_SCALE_FACTOR <= s <= MAX_SCALE_FACTOR) and _scale_shows(ate, s):
            warnings.append(
                f"aligned scale {s:.3g} is far from 1 although the {prior} prior is metric; "
                "the Sim(3) alignment hides a scale error"
            )
    return {
        "frames_posed_fraction": frac,
        "lost_spans": lost_spans(poses),
        "relocalised_at": relocalised_at(poses),
        "frames_posed_by_rotation": sum(p.status == "rotation" for p in poses),
        "warnings": warnings,
        "plausible": not warnings,
    }


def skip_warnings(meta: dict[str, Any]) -> list[str]:
    """The warning for the frames ``--skip-bad-frames`` skipped (``meta["skipped"]``: dicts
    with ``frame`` and ``reason``), or none."""
    skipped = meta.get("skipped") or []
    if not skipped:
        return []
    return [f"{len(skipped)} unreadable frame(s) skipped (the first: frame {skipped[0]['frame']})"]
