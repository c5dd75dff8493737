"""docs/upstream.md §13 — what a run leaves behind: trajectories, point cloud, summary, plot.

Files in the output folder, every one written atomically (temporary file, then rename):

* ``trajectory.txt`` — every frame that has a pose, in frame order (TUM ``timestamp tx ty tz
  qx qy qz qw``, camera-to-world, Sim(3) scale dropped); tracked frames are composed with their
  keyframe's *final* pose. Frames seen while lost have no pose and are not listed (counted
  in the summary as ``lost_frames``). Upstream writes keyframes only (users asked for all
  frames, docs/upstream.md §14).
* ``keyframes.txt`` — the keyframes, same format (upstream's ``<seq>.txt``); their images in
  ``keyframes/<timestamp>.png`` (upstream's ``keyframes/`` folder), at the working resolution.
* ``baseline_odometry.txt`` — with ``--baseline``: OpenCV's RGB-D odometry, TUM format.
* ``reconstruction.ply`` — per keyframe, world points ``T_WC · X_canon`` (ray-constrained in
  calibrated mode), colours from its image, pixels with average confidence ``C/N`` above
  ``output.C_conf_threshold`` (default 1.5, upstream's ``save_reconstruction``; pixels without
  a measurement have ``C = 1``: never exported, nor their filled-in depth, ``Keyframe.X_map``);
  a keyframe whose depth disagrees with those it overlaps by more than ``output.scale_tolerance``
  (log ratio, 0.2) is rescaled about its camera (``mslam.system.map_scale``); binary, x y z
  float32, red green blue uint8.
* ``summary.json`` — counts, timings, kernels, prior, path length, ATE (Sim(3), evo's pairs; per
  map segment too, ``Recovery.segment_ates``), rotations and trust (``mslam.system.health``).
* ``trajectory.png`` — estimate (aligned) and ground truth from the top, and the error over time.

Public names, in reading order:
    C_CONF_THRESHOLD, reconstruction_points, evaluate_run, summary_dict, plot_trajectory,
    write_outputs
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mslam.atomic import write_atomic
from mslam.datasets.frame import FrameSequence
from mslam.system.frontend import SlamSystem
from mslam_ref import sim3

__all__ = [
    "C_CONF_THRESHOLD",
    "SCALE_TOLERANCE",
    "keyframe_colours",
    "evaluate_run",
    "plot_trajectory",
    "reconstruction_points",
    "summary_dict",
    "write_outputs",
]

SCALE_TOLERANCE = 0.2  #: default of ``output.scale_tolerance`` (log ratio, ``system.map_scale``)

#: Default of ``output.C_conf_threshold``: exported points exceed it (upstream, §13).
C_CONF_THRESHOLD = 1.5


def keyframe_colours(system: SlamSystem, k: int) -> np.ndarray:
    """(H, W, 3) uint8 colours of keyframe ``k`` at its pointmap resolution (as the PLY's)."""
    kf = system.keyframes[k]
    H, W = kf.shape
    img = kf.frame.rgb
    if img.shape[:2] != (H, W) and hasattr(system.prior, "network_frame"):
        img = system.prior.network_frame(kf.frame).rgb  # the MASt3R adapter's resize/crop
    if img.shape[:2] != (H, W):
        img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)


def reconstruction_points(
    system: SlamSystem, c_thresh: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of all keyframes (upstream evaluate.py::save_reconstruction).

    Args:
        system: the finished run.
        c_thresh: keep pixels with ``C/N > c_thresh``; None reads the run's
            ``output.C_conf_threshold`` (default :data:`C_CONF_THRESHOLD`).

    Returns:
        xyz (P, 3) float32, rgb (P, 3) uint8.
    """
    from mslam.system.map_scale import scale_corrections
    from mslam_ref import fusion

    section = dict(system.cfg.sections.get("output", {}))
    if c_thresh is None:
        c_thresh = float(section.get("C_conf_threshold", C_CONF_THRESHOLD))
    tolerance = float(section.get("scale_tolerance", SCALE_TOLERANCE))

    if len(system.keyframes) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    X, C = system.keyframes.pointmaps(fusion, system.K, exported=True)
    factor = scale_corrections(X, C, system.keyframes.poses(), c_thresh, tolerance)
    xyz, rgb = [], []
    for k, kf in enumerate(system.keyframes):
        img = keyframe_colours(system, k)
        keep = (C[k] > c_thresh) & np.all(np.isfinite(X[k]), axis=-1)
        xyz.append(sim3.act(kf.T_WC, factor[k] * X[k][keep]))
        rgb.append(img[keep])
    return np.concatenate(xyz).astype(np.float32), np.concatenate(rgb).astype(np.uint8)


def _path_length(P: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) if len(P) > 1 else 0.0


def evaluate_run(system: SlamSystem, sequence: FrameSequence) -> dict[str, Any]:
    """ATE (Sim(3)) of all frames, of the keyframes and of each map segment; path lengths:
    ``path_length`` is the ground truth's, summed over steps between consecutive frames that
    both have a pose and ground truth (``FrameSequence.ground_truth``; else the estimate's)."""
    from mslam import evaluate, rotation_metrics

    idx, ts, T = system.frame_poses()
    out: dict[str, Any] = {"path_length_est": _path_length(T[:, :3]) if len(T) else 0.0}
    truth = sequence.ground_truth()
    if truth is None or len(T) < 3:
        out["path_length"] = out["path_length_est"]
        if truth is not None:
            out["evaluation_error"] = f"ATE not computed: too few posed frames ({len(T)}; 3 needed)"
        return out
    gt_idx, gt_ts, gt = truth
    # Ground truth over consecutive frames that both have a pose (a relocation jump is no path).
    has = np.zeros(len(sequence), bool)
    has[idx[idx < len(has)]] = True
    both = has[gt_idx[:-1]] & has[gt_idx[1:]] & (np.diff(gt_idx) == 1)
    steps = np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1)
    out["path_length"] = float(steps[both].sum())
    out["rotation"] = rotation_metrics.associated_report(ts, T, gt_ts, gt)  # needs no alignment
    try:
        res = evaluate.ate(ts, T, gt_ts, gt, align="sim3")
    except ValueError as exc:  # e.g. a pure rotation: reported, never fatal to the outputs
        out["evaluation_error"] = f"ATE not computed: {exc}"
        return out
    out["ate"] = res.to_dict()
    out["ate_percent_of_path"] = 100.0 * res.rmse / max(out["path_length"], 1e-12)
    out["ate_by_map"] = system.recovery.segment_ates(
        system.poses, len(system.keyframes), (idx, ts, T), (gt_ts, gt))  # fmt: skip
    _, kts, kT = system.keyframe_poses()
    if len(kT) >= 3:
        try:
            out["ate_keyframes"] = evaluate.ate(kts, kT, gt_ts, gt, align="sim3").to_dict()
        except ValueError as exc:
            out["evaluation_error"] = f"keyframe ATE not computed: {exc}"
    out["_ate_result"] = res
    out["_gt"] = (gt_ts, gt[:, :3])
    out["_gt_T"] = gt
    return out


def summary_dict(system: SlamSystem, meta: dict[str, Any], ev: dict[str, Any]) -> dict[str, Any]:
    """The JSON summary (docs/upstream.md §13 plus what users ask for, §14)."""
    st = system.stats
    graph, graph_checks = system.graph, system.backend.loop_checks
    spans = [e.j - e.i for e in graph.edges if e.kind == "retrieval"]
    seconds = float(meta.get("seconds", 0.0))
    frames = st.frames
    idx_posed, _, T_WC = system.frame_poses()
    out = {
        "source": meta.get("source"),
        "frames": frames,
        "frames_with_pose": len(T_WC),
        "keyframes": len(system.keyframes),
        "edges": len(graph),
        "edge_candidates_tested": graph.candidates_tested,
        "edge_candidates_rejected_unmatched": graph.candidates_rejected_early,
        "loop_closure_edges": graph.count("retrieval"),
        "longest_loop_closure_span": max(spans, default=0),
        "relocalisations": st.relocalisations,
        "reloc_attempts": st.reloc_attempts,
        "lost_frames": st.lost_frames,
        "skipped_frames": st.skipped_frames,
        "backend_solves": st.backend_solves,
        "seconds": seconds,
        "frames_per_second": frames / seconds if seconds > 0 else None,
        "stage_seconds": {k: round(v, 4) for k, v in sorted(st.seconds.items())},
        "kernels": system.kernels.name,
        "prior": meta.get("prior"),
        "prior_metric": bool(meta.get("prior_metric", False)),
        "device": meta.get("device", "cpu"),
        "calibrated": system.K is not None,
        "resolution": list(system.keyframes[0].shape[::-1]) if len(system.keyframes) else None,
        "interrupted": bool(meta.get("interrupted", False)),
        "path_length": ev.get("path_length"),
        "path_length_est": ev.get("path_length_est"),
        "rotation": ev.get("rotation"),
    }
    from mslam.system.divergence import divergence_report
    from mslam.system.health import health_report, skip_warnings

    posed, ate, metric = out["frames_with_pose"], ev.get("ate"), out["prior_metric"]
    out.update(health_report(system.poses, frames, posed, out["prior"], ate, metric=metric))
    maps = system.recovery.report(system.poses, len(system.keyframes))  # mslam.system.recovery
    out["maps"] = maps["maps"]
    warnings = [*out["warnings"], *maps["warnings"], *skip_warnings(meta)]
    out.update(divergence_report(system.divergence, graph_checks, T_WC, warnings, idx_posed, maps))
    if "ate" in ev:
        out["ate"] = ev["ate"]
        out["ate_rmse"] = ev["ate"]["ate_rmse"]
        out["ate_frames"] = ev["ate"]["matched"]
        out["ate_percent_of_path"] = ev["ate_percent_of_path"]
        for key in ("ate_keyframes", "ate_by_map"):  # the latter with several maps only
            if ev.get(key) is not None:
                out[key] = ev[key]
    if "evaluation_error" in ev:
        out["evaluation_error"] = ev["evaluation_error"]
    for key in ("skipped", "depth_scale_assumed"):
        if meta.get(key):
            out[key] = meta[key]
    for key in ("colour_registration", "focal_estimate", "baseline", "config"):
        if key in meta:
            out[key] = {k: v for k, v in meta[key].items() if not k.startswith("_")}
    return out


def plot_trajectory(
    system: SlamSystem,
    ev: dict[str, Any],
    title: str = "",
    baseline: Any = None,
    metric: bool = True,
) -> bytes:
    """PNG bytes: top view and the position error over time, both panels labelled.

    Axes are in metres when the estimate is aligned to ground truth or ``metric`` (a depth-based
    prior, ``mslam.priors.base.is_metric``), else in "arbitrary units" (RGB-only priors
    fix the scale only up to a factor).

    Top view (the plane of the two largest principal directions of the ground truth, else of
    the estimate): ground truth, the Sim(3)-aligned estimate, keyframes, loop-closure edges
    (retrieval and relocalisation edges), start and end markers, the ground truth of frames
    seen while lost, the ``--baseline`` odometry when it ran. Error panel: lost spans shaded.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from mslam.system.health import lost_spans

    _, ts, T = system.frame_poses()
    res = ev.get("_ate_result")
    fig, axes = plt.subplots(1, 2 if res is not None else 1, figsize=(12 if res else 6, 5.2))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    spans = lost_spans(system.poses)
    if res is not None:
        gt_ts, gt_P = ev["_gt"]
        c = gt_P.mean(0)
        B = np.linalg.svd(gt_P - c, full_matrices=True)[2][:2].T
        top = lambda P: (np.asarray(P) - c) @ B
        align = lambda P: res.scale * np.asarray(P) @ res.rotation.T + res.translation
        ax.plot(*top(gt_P).T, "-", color="0.6", lw=2, label="ground truth")
        est2 = top(res.aligned_positions)
        _plot_lost_gt(ax, spans, system.poses, gt_ts, top(gt_P))
        if baseline is not None and len(baseline.T_WC) >= 3:
            from mslam import evaluate

            b = evaluate.ate(baseline.timestamps, baseline.T_WC, gt_ts, ev["_gt_T"], "sim3")
            ax.plot(*top(b.aligned_positions).T, "--", color="C2", lw=1, label="RGB-D odometry")
        ax.plot(*est2.T, "-", color="C3", lw=1, label="estimate (Sim(3)-aligned)")
        _plot_keyframes(ax, system, lambda P: top(align(P)))
        _plot_start_end(ax, est2)
        ax2 = axes[1]
        t_err, err = ts[res.est_index], res.errors * 100.0
        gap = np.flatnonzero(np.diff(t_err) > 1.5 * np.median(np.diff(t_err))) + 1
        t_err, err = np.insert(t_err, gap, np.nan), np.insert(err, gap, np.nan)
        ax2.plot(t_err, err, ".-", ms=2, color="C3", label="position error")
        _shade_lost(ax2, spans, system.poses, gt_ts)
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("position error [cm]")
        ax2.set_title(
            f"ATE RMSE {res.rmse * 100:.2f} cm over {res.matched} of {system.stats.frames} "
            f"frames (scale {res.scale:.3f})"
        )
        ax2.legend(loc="best", fontsize=8)
        ax2.grid(alpha=0.3)
    elif len(T):
        P = T[:, :3]
        c = P.mean(0)
        B = np.linalg.svd(P - c, full_matrices=True)[2][:2].T
        p2 = (P - c) @ B
        ax.plot(*p2.T, ".-", color="C3", ms=2, label="estimate (no ground truth)")
        _plot_keyframes(ax, system, lambda Q: (np.asarray(Q) - c) @ B)
        _plot_start_end(ax, p2)
    unit = "m" if res is not None or metric else "arbitrary units"
    ax.set_xlabel(f"first principal direction [{unit}]")
    ax.set_ylabel(f"second principal direction [{unit}]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{title or 'trajectory'}: top view")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # nothing to name when no frame has a pose
        ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def _plot_keyframes(ax: Any, system: SlamSystem, to2d: Any) -> None:
    """Keyframe dots and one line per loop-closure (retrieval / reloc) edge."""
    if len(system.keyframes) == 0:
        return
    K2 = to2d(system.keyframes.poses()[:, :3])
    ax.plot(*K2.T, "o", ms=3, color="C0", label="keyframes")
    first = True
    for e in system.graph.edges:
        if e.kind in ("retrieval", "reloc") and max(e.i, e.j) < len(K2):
            label = "loop-closure edges" if first else None
            ax.plot(*K2[[e.i, e.j]].T, "-", color="C1", lw=0.8, alpha=0.8, label=label)
            first = False


def _plot_start_end(ax: Any, P2: np.ndarray) -> None:
    if len(P2):
        ax.plot(*P2[0], "^", ms=9, color="green", label="start")
        ax.plot(*P2[-1], "s", ms=8, color="black", label="end")


def _gt_rows(spans: list[list[int]], poses: list[Any], gt_ts: np.ndarray) -> list[np.ndarray]:
    """Ground-truth row indices of each lost span (nearest stamp)."""
    stamp = {int(p.index): float(p.timestamp) for p in poses}
    out = []
    for a, b in spans:
        t0, t1 = stamp.get(a), stamp.get(b)
        if t0 is not None and t1 is not None and len(gt_ts):
            out.append(np.flatnonzero((gt_ts >= t0 - 1e-6) & (gt_ts <= t1 + 1e-6)))
    return out


def _plot_lost_gt(ax: Any, spans: list, poses: list, gt_ts: np.ndarray, gt2: np.ndarray) -> None:
    first = True
    for rows in _gt_rows(spans, poses, gt_ts):
        if len(rows):
            label = "lost (ground truth shown)" if first else None
            ax.plot(*gt2[rows].T, "x", ms=4, color="C4", label=label)
            first = False


def _shade_lost(ax: Any, spans: list, poses: list, gt_ts: np.ndarray) -> None:
    stamp = {int(p.index): float(p.timestamp) for p in poses}
    for k, (a, b) in enumerate(spans):
        label = "lost" if k == 0 else None
        ax.axvspan(stamp[a], stamp[b], color="C4", alpha=0.2, label=label)


def write_outputs(
    out_dir: str | Path, system: SlamSystem, sequence: FrameSequence, meta: dict[str, Any]
) -> dict[str, Any]:
    """Compute every output in memory, then write each file atomically; returns the summary."""
    from mslam import formats as mio

    out_dir = Path(out_dir)
    _, ts, T = system.frame_poses()
    _, kts, kT = system.keyframe_poses()
    xyz, rgb = reconstruction_points(system)
    ev = evaluate_run(system, sequence)
    summary = summary_dict(system, meta, ev)
    base = (meta.get("baseline") or {}).get("_result")
    metric = bool(meta.get("prior_metric", False))
    png = plot_trajectory(system, ev, str(meta.get("source", "")), base, metric)
    text = json.dumps(_finite(summary), indent=2, default=_json_default, allow_nan=False) + "\n"
    out_dir.mkdir(parents=True, exist_ok=True)
    mio.write_tum(out_dir / "trajectory.txt", ts, T.reshape(-1, 8))
    mio.write_tum(out_dir / "keyframes.txt", kts, kT.reshape(-1, 8))
    if base is not None:
        mio.write_tum(out_dir / "baseline_odometry.txt", base.timestamps, base.T_WC.reshape(-1, 8))
    for t, kf in zip(kts, system.keyframes):  # upstream's keyframes/ folder, named by stamp
        ok, enc = cv2.imencode(".png", np.ascontiguousarray(kf.frame.rgb[..., ::-1]))
        if ok:
            write_atomic(out_dir / "keyframes" / f"{t:.6f}.png", enc.tobytes())
    mio.write_ply(out_dir / "reconstruction.ply", xyz, rgb)
    write_atomic(out_dir / "trajectory.png", png)
    write_atomic(out_dir / "summary.json", text)
    return summary


def _finite(o: Any) -> Any:
    """``o`` with every non-finite float replaced by None (strict JSON: no NaN, no Infinity)."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    if isinstance(o, float | np.floating) and not np.isfinite(o):
        return None
    return o


def _json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
