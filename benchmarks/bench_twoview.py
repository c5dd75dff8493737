"""RGB-only runs with the two-view prior, beside the RGB-D prior and OpenCV odometry.

Runs (single passes, fast kernels, Taichi compiled by a warm-up run first):

1. the 7-Scenes clip (redkitchen frames 0-149, ``--data``), RGB only (`--prior twoview`, its
   packaged config: 160x120), uncalibrated (60° focal guess inside the prior) and calibrated
   (`--calib calib.yaml`); the RGB-D prior (`--config rgbd`) and OpenCV's frame-to-frame RGB-D
   odometry on the same frames for comparison;
2. the synthetic loop rendered to a TUM folder (`mslam synth loop --frames N --out DIR`) and
   run RGB-only (depth ignored), uncalibrated and calibrated (the folder's calib.yaml).

For every run: frames with a pose, Sim(3)-aligned ATE, loop-closure edges, and the spread of
the keyframes' pointmap scale against ground-truth depth (std of log(s_k · median z_k /
median z_gt)) with the keyframe poses from tracking alone and after the backend.

Usage: ``python benchmarks/bench_twoview.py [--loop-frames N] [--data DIR]`` (writes the section
"twoview" of RESULTS.md).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _data import add_data_argument, seven_scenes
from _results import table, write_section
from bench_system import baseline_figures

from mslam import evaluate
from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam


def keyframe_scale_spread(system, depth_seq=None) -> tuple[float, float]:
    """Std of log keyframe pointmap scale vs ground-truth depth: (tracking only, final).

    ``depth_seq``: the same frames with depth (the two-view prior's frames carry none)."""
    out = []
    for attr in ("T_WC_init", "T_WC"):
        logs = []
        for kf in system.keyframes:
            f = kf.frame if depth_seq is None else depth_seq[kf.frame.index]
            z_gt, (H, W) = f.depth, kf.shape
            if z_gt is None:
                return float("nan"), float("nan")
            z = kf.state.X_canon.reshape(H, W, 3)[..., 2]
            ok = (z_gt > 0) & (z > 0)
            logs.append(np.log(getattr(kf, attr)[7] * np.median(z[ok]) / np.median(z_gt[ok])))
        out.append(float(np.std(logs)))
    return out[0], out[1]


def one_run(source: str, prior: str, calib: str | None = None, baseline: bool = False) -> dict:
    cfg = load_config(prior if prior in ("rgbd", "twoview") else None)
    src = open_source(source, cfg, calib, prior)
    if src.K is not None:
        cfg = replace(cfg, use_calib=True)
    t0 = time.perf_counter()
    system, _ = run_slam(src, cfg, load_kernels("fast"))
    seconds = time.perf_counter() - t0
    seq = src.sequence
    idx, ts, T = system.frame_poses()
    ate = evaluate.ate(ts, T, seq.timestamps, seq.T_WC) if len(ts) >= 3 else None
    path = float(np.linalg.norm(np.diff(seq.T_WC[:, :3], axis=0), axis=1).sum())
    try:  # the same frames with their depth, for the scale check only
        depth_seq = open_source(source, cfg, calib, "rgbd").sequence
    except ValueError:
        depth_seq = None
    spread = keyframe_scale_spread(system, depth_seq)
    row = {
        "prior": prior,
        "calibrated": system.K is not None,
        "frames": len(seq),
        "posed": len(idx),
        "kf": len(system.keyframes),
        "loops": system.graph.count("retrieval"),
        "span": max((e.j - e.i for e in system.graph.edges if e.kind == "retrieval"), default=0),
        "relocs": system.stats.relocalisations,
        "ate": None if ate is None else ate.rmse,
        "path": path,
        "seconds": seconds,
        "spread": spread,
    }
    if baseline:
        row["baseline"] = baseline_figures(seq, ts)
    return row


def fmt(x, spec=".4f"):
    return "–" if x is None or not np.isfinite(x) else format(x, spec)


def body_row(name: str, r: dict) -> list:
    pct = None if r["ate"] is None else 100 * r["ate"] / r["path"]
    return [
        name,
        f"{r['posed']} / {r['frames']} ({100 * r['posed'] / r['frames']:.0f} %)",
        r["kf"],
        f"{r['loops']} ({r['span']})",
        r["relocs"],
        fmt(r["ate"]),
        f"{fmt(pct, '.2f')} %",
        f"{fmt(r['spread'][0], '.3f')} → {fmt(r['spread'][1], '.3f')}",
        f"{r['seconds']:.0f}",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loop-frames", type=int, default=240, help="frames of the rendered loop")
    add_data_argument(ap)
    args = ap.parse_args()
    clip = seven_scenes(args.data)
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    one_run("synthetic:loop:8:64x48", "synthetic")  # warm-up: compile the Taichi kernels
    rows = []
    if clip.is_dir():
        calib = str(clip / "calib.yaml")
        for name, prior, cal in (
            ("7-Scenes, twoview, uncalibrated", "twoview", None),
            ("7-Scenes, twoview, calibrated", "twoview", calib),
            ("7-Scenes, RGB-D prior, uncalibrated", "rgbd", None),
        ):
            rows.append((name, one_run(str(clip), prior, cal, baseline=prior == "rgbd")))
            print(name, {k: v for k, v in rows[-1][1].items()}, flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        from mslam.datasets.synthetic import make_sequence
        from mslam.datasets.tum import write_tum_sequence

        folder = Path(tmp) / "loop"
        write_tum_sequence(make_sequence("loop", args.loop_frames, 160, 120, 0), folder)
        for cal in (None, str(folder / "calib.yaml")):
            mode = "calibrated" if cal else "uncalibrated"
            name = f"synthetic loop folder ({args.loop_frames} frames, 160x120), twoview, {mode}"
            rows.append((name, one_run(str(folder), "twoview", cal)))
            print(name, rows[-1][1], flush=True)

    header = ["run", "frames with pose", "keyframes", "loop edges (longest span)", "relocs", "ATE [m]",
              "ATE / path", "keyframe log-scale std (tracking → final)", "seconds"]  # fmt: skip
    text = table(header, [body_row(n, r) for n, r in rows])
    base = next((r["baseline"] for _, r in rows if "baseline" in r), None)
    if base is not None and "ate_rmse" in base:
        text += (
            f"\n\nOpenCV RGB-D odometry (frame to frame, uses depth) on the same 7-Scenes frames: "
            f"ATE {base['ate_rmse']:.4f} m."
        )
    text += (
        "\n\nATE: Sim(3)-aligned RMSE over the frames with a pose. Keyframe log-scale std: the "
        "spread over keyframes of log(s_k · median z_k / median z_gt), keyframe pointmap z "
        "against ground-truth depth (never read by the twoview prior), with the pose each "
        "keyframe was created with and with its final pose. Frames that waited for parallax "
        "at the start are tracked once the first two keyframes exist; frames with too little "
        "parallax to both last keyframes are posed by the pair's rotation with zero "
        'translation (docs/priors.md, "Two-view prior").'
    )
    write_section("twoview", "Two-view prior, RGB only", text)


if __name__ == "__main__":
    main()
