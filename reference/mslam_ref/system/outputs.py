"""Spec §13 — what a run leaves behind: trajectories, point cloud, summary, plot.

Files in the output folder, every one written atomically (temporary file, then rename):

* ``trajectory.txt`` — every frame that has a pose (TUM ``timestamp tx ty tz qx qy qz qw``,
  camera-to-world, Sim(3) scale dropped); tracked frames are composed with their keyframe's
  *final* pose. Frames seen while tracking was lost have no pose and are not listed (counted
  in the summary as ``lost_frames``). Upstream writes keyframes only (users asked for all
  frames, spec §14).
* ``keyframes.txt`` — the keyframes, same format (upstream's ``<seq>.txt``).
* ``reconstruction.ply`` — per keyframe, world points ``T_WC · X_canon`` (ray-constrained in
  calibrated mode), colours from the keyframe image, pixels with ``C/N > 1.5`` (upstream's
  ``save_reconstruction``); binary little-endian, x y z float32, red green blue uint8.
* ``summary.json`` — counts, timings, kernels, prior, ATE (Sim(3) Umeyama, evo's association)
  when ground truth exists, path length.
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

from mslam_ref import sim3
from mslam_ref.commands import write_atomic

__all__ = [
    "C_CONF_THRESHOLD",
    "evaluate_run",
    "plot_trajectory",
    "reconstruction_points",
    "summary_dict",
    "write_outputs",
]

#: Average-confidence threshold of the exported points (upstream viz default, spec §13).
C_CONF_THRESHOLD = 1.5


def reconstruction_points(
    system: Any, c_thresh: float = C_CONF_THRESHOLD
) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of all keyframes (upstream evaluate.py::save_reconstruction).

    Returns:
        xyz (P, 3) float32, rgb (P, 3) uint8.
    """
    from mslam_ref import fusion

    if len(system.keyframes) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    X, C = system.keyframes.pointmaps(fusion, system.K)
    xyz, rgb = [], []
    for k, kf in enumerate(system.keyframes):
        H, W = kf.shape
        img = kf.frame.rgb
        if img.shape[:2] != (H, W) and hasattr(system.prior, "network_frame"):
            img = system.prior.network_frame(kf.frame).rgb  # the MASt3R adapter's resize/crop
        if img.shape[:2] != (H, W):
            img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        keep = (C[k] > c_thresh) & np.all(np.isfinite(X[k]), axis=-1)
        xyz.append(sim3.act(kf.T_WC, X[k][keep]))
        rgb.append(img[keep])
    return np.concatenate(xyz).astype(np.float32), np.concatenate(rgb).astype(np.uint8)


def _path_length(P: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) if len(P) > 1 else 0.0


def evaluate_run(system: Any, sequence: Any) -> dict[str, Any]:
    """ATE (Sim(3)) of all frames and of the keyframes against ground truth, path lengths.

    ``path_length`` is the ground truth's, summed over steps between consecutive frames that
    both have a pose (or the estimate's when there is no ground truth).
    """
    from mslam_ref import evaluate

    idx, ts, T = system.frame_poses()
    out: dict[str, Any] = {"path_length_est": _path_length(T[:, :3]) if len(T) else 0.0}
    gt = getattr(sequence, "T_WC", None)
    if gt is None or len(T) < 3:
        out["path_length"] = out["path_length_est"]
        return out
    gt = np.asarray(gt)
    gt_ts = np.asarray(sequence.timestamps, dtype=np.float64)
    # Ground-truth path over consecutive frames that both have a pose (a relocation jump
    # between lost frames does not count as path).
    has = np.zeros(len(gt), bool)
    has[idx[idx < len(gt)]] = True
    steps = np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1)
    out["path_length"] = float(steps[has[:-1] & has[1:]].sum())
    try:
        res = evaluate.ate(ts, T, gt_ts, gt, align="sim3")
    except ValueError as exc:  # e.g. a pure rotation: reported, never fatal to the outputs
        out["evaluation_error"] = f"ATE not computed: {exc}"
        return out
    out["ate"] = res.to_dict()
    out["ate_percent_of_path"] = 100.0 * res.rmse / max(out["path_length"], 1e-12)
    _, kts, kT = system.keyframe_poses()
    if len(kT) >= 3:
        try:
            out["ate_keyframes"] = evaluate.ate(kts, kT, gt_ts, gt, align="sim3").to_dict()
        except ValueError as exc:
            out["evaluation_error"] = f"keyframe ATE not computed: {exc}"
    out["_ate_result"] = res
    out["_gt"] = (gt_ts, gt[:, :3])
    return out


def summary_dict(system: Any, meta: dict[str, Any], ev: dict[str, Any]) -> dict[str, Any]:
    """The JSON summary (spec §13 plus what users ask for, §14)."""
    st = system.stats
    graph = system.graph
    spans = [e.j - e.i for e in graph.edges if e.kind == "retrieval"]
    seconds = float(meta.get("seconds", 0.0))
    frames = st.frames
    out = {
        "source": meta.get("source"),
        "frames": frames,
        "frames_with_pose": len(system.frame_poses()[0]),
        "keyframes": len(system.keyframes),
        "edges": len(graph),
        "edge_candidates_tested": graph.candidates_tested,
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
        "kernel_fallbacks": list(system.kernels.fallbacks),
        "prior": meta.get("prior"),
        "calibrated": system.K is not None,
        "resolution": list(system.keyframes[0].shape[::-1]) if len(system.keyframes) else None,
        "interrupted": bool(meta.get("interrupted", False)),
        "path_length": ev.get("path_length"),
        "path_length_est": ev.get("path_length_est"),
    }
    if "ate" in ev:
        out["ate"] = ev["ate"]
        out["ate_rmse"] = ev["ate"]["ate_rmse"]
        out["ate_percent_of_path"] = ev["ate_percent_of_path"]
        if "ate_keyframes" in ev:
            out["ate_keyframes"] = ev["ate_keyframes"]
    if "evaluation_error" in ev:
        out["evaluation_error"] = ev["evaluation_error"]
    if meta.get("skipped"):
        out["skipped"] = meta["skipped"]
    for key in ("baseline", "config"):
        if key in meta:
            out[key] = meta[key]
    return out


def plot_trajectory(system: Any, ev: dict[str, Any], title: str = "") -> bytes:
    """PNG bytes: top view (estimate aligned to ground truth) and the error over time."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    _, ts, T = system.frame_poses()
    res = ev.get("_ate_result")
    fig, axes = plt.subplots(1, 2 if res is not None else 1, figsize=(11 if res else 6, 5))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    if res is not None:
        _gt_ts, gt_P = ev["_gt"]
        est_P = res.aligned_positions
        # Top view: the plane of the two largest principal directions of the ground truth.
        c = gt_P.mean(0)
        _, _, Vt = np.linalg.svd(gt_P - c, full_matrices=True)
        B = Vt[:2].T
        g2, e2 = (gt_P - c) @ B, (est_P - c) @ B
        ax.plot(g2[:, 0], g2[:, 1], "-", color="0.5", lw=2, label="ground truth")
        ax.plot(e2[:, 0], e2[:, 1], "-", color="C3", lw=1, label="estimate (Sim(3)-aligned)")
        kf_ts = {float(kf.frame.timestamp) for kf in system.keyframes}
        is_kf = np.array([float(t) in kf_ts for t in ts[res.est_index]])
        ax.plot(e2[is_kf, 0], e2[is_kf, 1], "o", ms=3, color="C0", label="keyframes")
        ax2 = axes[1]
        ax2.plot(ts[res.est_index], res.errors * 100.0, color="C3")
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel("position error [cm]")
        ax2.set_title(f"ATE RMSE {res.rmse * 100:.2f} cm (scale {res.scale:.3f})")
        ax2.grid(alpha=0.3)
    elif len(T):
        P = T[:, :3]
        c = P.mean(0)
        _, _, Vt = np.linalg.svd(P - c, full_matrices=True)
        p2 = (P - c) @ Vt[:2].T
        ax.plot(p2[:, 0], p2[:, 1], ".-", color="C3", label="estimate")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title or "trajectory, top view")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def write_outputs(
    out_dir: str | Path, system: Any, sequence: Any, meta: dict[str, Any]
) -> dict[str, Any]:
    """Compute every output in memory, then write each file atomically; returns the summary."""
    from mslam_ref import io as mio

    out_dir = Path(out_dir)
    _, ts, T = system.frame_poses()
    _, kts, kT = system.keyframe_poses()
    xyz, rgb = reconstruction_points(system)
    ev = evaluate_run(system, sequence)
    summary = summary_dict(system, meta, ev)
    png = plot_trajectory(system, ev, title=str(meta.get("source", "")))
    text = json.dumps(_finite(summary), indent=2, default=_json_default, allow_nan=False) + "\n"
    out_dir.mkdir(parents=True, exist_ok=True)
    mio.write_tum(out_dir / "trajectory.txt", ts, T.reshape(-1, 8))
    mio.write_tum(out_dir / "keyframes.txt", kts, kT.reshape(-1, 8))
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
