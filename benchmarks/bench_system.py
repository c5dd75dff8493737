"""Acceptance runs of the whole system: accuracy, loop closure, relocalisation, speed.

Runs (each a single pass; a run takes seconds to minutes, so times are single runs with the
Taichi kernels compiled beforehand by a warm-up run):

1. built-in synthetic ``loop`` (the ``mslam run`` default), synthetic prior, ``fast`` and ``ref``
   kernels: ATE (Sim(3)) / path length (< 1%), loop-closure edges (>= 1), fast vs ref time (>= 5x);
2. synthetic ``jump`` (the kidnapped camera: relocalisation within 5 frames of the jump, >= 90 %
   of frames posed) and ``detour`` (20 unmapped frames; relocalisation at the return frame):
   relocalisations (>= 1), lost frames and ATE / path (< 2%);
3. the 7-Scenes clip (redkitchen frames 0-149, ``--data``), RGB-D prior with the packaged
   ``rgbd`` config, uncalibrated and calibrated, beside OpenCV's frame-to-frame RGB-D odometry
   on the same frames.

Usage: ``python benchmarks/bench_system.py [--quick] [--no-ref] [--data DIR]`` (``--quick``:
smaller runs, for a smoke test; the RESULTS.md section is only written by a full run; ``--data``:
the data folder, default ``$MSLAM_DATA``, see ``_data.py``).

``python benchmarks/bench_system.py --resolution 512 [--frames N] [--ref-frames 20]`` instead
profiles 7-Scenes at that working resolution for the fast kernels (float64, float32, with the
background backend) and the reference kernels: frames per second, ATE, peak memory, frame-time
flatness and the stage table (``_resolution.py``; section ``system-<N>`` of RESULTS.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _data import add_data_argument, data_dir, seven_scenes
from _results import table, write_section

from mslam.config import load_config
from mslam.datasets.synthetic import DEFAULT_SYNTHETIC
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.outputs import evaluate_run


def one_run(source, kernels, overrides=(), config=None, calib=None, baseline=False):
    """Run the system once; returns a dict of the figures reported."""
    cfg = load_config(config, list(overrides))
    src = open_source(source, cfg, calib)
    if calib is not None or src.K is not None:
        from dataclasses import replace

        cfg = replace(cfg, use_calib=src.K is not None)
    t0 = time.perf_counter()
    system, _ = run_slam(src, cfg, load_kernels(kernels))
    seconds = time.perf_counter() - t0
    ev = evaluate_run(system, src.sequence)
    row = {
        "source": source if source else "synthetic:" + DEFAULT_SYNTHETIC[0],
        "kernels": kernels,
        "frames": system.stats.frames,
        "kf": len(system.keyframes),
        "loops": system.graph.count("retrieval"),
        "span": max((e.j - e.i for e in system.graph.edges if e.kind == "retrieval"), default=0),
        "relocs": system.stats.relocalisations,
        "lost": system.stats.lost_frames,
        "seconds": seconds,
        "fps": system.stats.frames / seconds,
        "ate": ev.get("ate", {}).get("ate_rmse"),
        "path": ev.get("path_length"),
        "pct": ev.get("ate_percent_of_path"),
        "stages": dict(system.stats.seconds),
        "calibrated": system.K is not None,
    }
    if baseline:
        row["baseline"] = baseline_figures(src.sequence, system.frame_poses()[1])
    return row


def baseline_figures(seq, slam_stamps):
    """OpenCV RGB-D odometry ATE on all frames and on the frames the SLAM run has poses for."""
    import numpy as np

    from mslam import evaluate
    from mslam.baselines import rgbd_odometry

    try:
        res = rgbd_odometry(seq)
    except Exception as exc:  # the baseline is optional
        return {"error": str(exc).strip().splitlines()[-1]}
    out = {"failures": res.failures, "seconds": res.seconds}
    a = evaluate.ate(res.timestamps, res.T_WC, seq.timestamps, seq.T_WC)
    out["ate_rmse"] = a.rmse
    same = np.isin(res.timestamps, slam_stamps)
    out["ate_rmse_same_frames"] = a.rmse
    if 3 <= same.sum() < len(same):
        b = evaluate.ate(res.timestamps[same], res.T_WC[same], seq.timestamps, seq.T_WC)
        out["ate_rmse_same_frames"] = b.rmse
    return out


def fmt(x, spec=".3f"):
    return "–" if x is None else format(x, spec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small runs; do not write RESULTS.md")
    ap.add_argument("--no-ref", action="store_true", help="skip the (slow) reference-kernel run")
    ap.add_argument(
        "--resolution",
        type=int,
        help="instead: 7-Scenes at this long side (e.g. 512), FPS and stage table per kernel set",
    )
    ap.add_argument("--frames", type=int, help="with --resolution: the first N frames only")
    ap.add_argument(
        "--config",
        help="with --resolution: the config (default: rgbd_512 from 400 px up, rgbd_256 from "
        "200 px, else rgbd)",
    )
    ap.add_argument(
        "--ref-frames", type=int, default=20, help="with --resolution: frames for the ref kernels"
    )
    add_data_argument(ap)
    args = ap.parse_args()
    clip = seven_scenes(args.data)
    if args.resolution:
        from _resolution import resolution_bench

        default = "rgbd_512" if args.resolution >= 400 else "rgbd_256"
        config = args.config or (default if args.resolution >= 200 else "rgbd")
        n_ref = 0 if args.no_ref else args.ref_frames
        text = resolution_bench(args.resolution, args.frames, n_ref, config, data_dir(args.data))
        print(text)
        if not args.frames:
            title = f"Whole system at {args.resolution} px long side"
            write_section(f"system-{args.resolution}", title, text)
        return
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    loop = "synthetic:loop:24:64x48" if args.quick else None  # None = the built-in default
    size = "32:64x48" if args.quick else "80:128x96"
    one_run("synthetic:loop:8:64x48", "fast")  # warm-up: compile the Taichi kernels

    rows = []
    rows.append(one_run(loop, "fast"))
    print(rows[-1], flush=True)
    if not args.no_ref:
        rows.append(one_run(loop, "ref"))
        print(rows[-1], flush=True)
    for path in ("jump", "detour"):
        rows.append(one_run(f"synthetic:{path}:{size}", "fast"))
        print(rows[-1], flush=True)
    real = []
    if clip.is_dir():
        ov = ["dataset.long_side=" + ("96" if args.quick else "160")]
        if args.quick:
            ov.append("dataset.subsample=3")
        for calib in (None, str(clip / "calib.yaml")):
            r = one_run(str(clip), "fast", ov, config="rgbd", calib=calib, baseline=True)
            real.append(r)
            print({k: v for k, v in r.items() if k != "stages"}, flush=True)

    header = [
        "run",
        "kernels",
        "frames",
        "keyframes",
        "loop edges (longest span)",
        "relocs",
        "lost",
        "ATE [m]",
        "path [m]",
        "ATE / path",
        "seconds",
        "frames/s",
    ]
    body_rows = [
        [
            r["source"],
            r["kernels"],
            r["frames"],
            r["kf"],
            f"{r['loops']} ({r['span']})",
            r["relocs"],
            r["lost"],
            fmt(r["ate"], ".4f"),
            fmt(r["path"], ".2f"),
            fmt(r["pct"], ".2f") + " %",
            f"{r['seconds']:.1f}",
            f"{r['fps']:.2f}",
        ]
        for r in rows
    ]
    text = table(header, body_rows)
    fast_loop = rows[0]
    ref_loop = next((r for r in rows if r["kernels"] == "ref"), None)
    if ref_loop is not None:
        text += (
            f"\n\nEnd to end on the default loop: ref {ref_loop['seconds']:.1f} s, fast "
            f"{fast_loop['seconds']:.1f} s: **{ref_loop['seconds'] / fast_loop['seconds']:.1f}x**"
            " (same keyframes and edges expected; see tests/system/test_system.py)."
        )
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in sorted(fast_loop["stages"].items()))
    text += f"\n\nWhere the time goes (fast, default loop): {stages}."
    if real:
        text += (
            "\n\n7-Scenes redkitchen frames 0-149 (150 frames, RGB-D prior, 160x120, "
            "`--config rgbd`):\n\n"
        )
        header = [
            "mode",
            "frames with pose",
            "keyframes",
            "loop edges",
            "relocs",
            "SLAM ATE [m]",
            "odometry ATE [m], all frames",
            "odometry ATE [m], SLAM's frames",
            "path [m]",
            "seconds",
        ]
        body = []
        for r in real:
            b = r["baseline"]
            body.append(
                [
                    "calibrated" if r["calibrated"] else "uncalibrated",
                    f"{r['frames'] - r['lost']} / {r['frames']}",
                    r["kf"],
                    r["loops"],
                    r["relocs"],
                    fmt(r["ate"], ".4f"),
                    fmt(b.get("ate_rmse"), ".4f"),
                    fmt(b.get("ate_rmse_same_frames"), ".4f"),
                    fmt(r["path"], ".2f"),
                    f"{r['seconds']:.1f}",
                ]
            )
        text += table(header, body)
        text += (
            "\n\nATEs are Sim(3)-aligned RMSE over the frames with a pose (evo's association, "
            "10 ms); the odometry (OpenCV RGB-D, frame to frame) runs on the same resized frames "
            "and is also scored on exactly the frames the SLAM run has poses for."
        )
    if args.quick:
        print(text)
        return
    write_section("system", "SLAM system end to end (acceptance runs)", text)
    print(text)


if __name__ == "__main__":
    main()
