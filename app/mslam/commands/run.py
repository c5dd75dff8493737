"""``mslam run`` — the SLAM system on a sequence, with outputs in ``--out DIR`` (docs/upstream.md §13).

::

    mslam run [SOURCE] --out DIR [--config FILE] [--kernels ref|fast] [--device cpu|cuda]
              [--calib FILE]
              [--prior synthetic|rgbd|mast3r|twoview] [--set SECTION.KEY=VALUE ...]
              [--max-frames N] [--baseline] [--quiet]

SOURCE: nothing (the built-in synthetic ``loop``), ``synthetic:NAME[:FRAMES[:WxH]]``, a
TUM-layout folder, a 7-Scenes folder, an image folder or a video file. Everything that can be
checked is checked before the first frame (config keys, calibration, prior); a bad input is
one line on stderr, exit code 2, and no output file. The output set is written into a temporary
folder beside ``--out`` and moved into place in one rename (``mslam.outdir``); an
existing non-empty ``--out`` is refused unless ``--overwrite``. Ctrl-C stops at the next frame
boundary, writes a complete set marked ``"interrupted": true`` and exits 130; a second Ctrl-C
stops at once and leaves no output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``run`` sub-command."""
    p = subparsers.add_parser(
        "run",
        help="run the SLAM system on a sequence",
        description="Run MASt3R-SLAM (single process) on SOURCE and write trajectory.txt, "
        "keyframes.txt, reconstruction.ply, summary.json and trajectory.png into --out.",
    )
    p.add_argument(
        "source",
        nargs="?",
        default=None,
        metavar="SOURCE",
        help="synthetic:NAME[:FRAMES[:WxH]], a TUM/7-Scenes folder, an image folder or a "
        "video file (default: the built-in synthetic loop)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--config",
        metavar="FILE",
        help="YAML config (inherit: base.yaml); 'base', 'calib', 'rgbd', 'rgbd_256', 'rgbd_512' "
        "and 'twoview' name the packaged files (default: base, or the prior's own for rgbd and "
        "twoview)",
    )
    p.add_argument(
        "--kernels",
        choices=("ref", "fast"),
        default="fast",
        help="kernel set: NumPy reference or Taichi (default: fast)",
    )
    p.add_argument(
        "--precision",
        choices=("f64", "f32"),
        default="f64",
        help="float type of the fast kernels (f32: matching ~1.5x faster; default: f64)",
    )
    p.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        default="cpu",
        help="where the fast kernels (Taichi) and the MASt3R network (torch) run; cuda needs an "
        "NVIDIA GPU and is refused without one (default: cpu)",
    )
    p.add_argument(
        "--calib",
        metavar="FILE",
        help="intrinsics YAML (width, height, "
        "calibration: [fx, fy, cx, cy, ...]); turns on calibrated mode",
    )
    p.add_argument(
        "--prior",
        choices=("synthetic", "rgbd", "mast3r", "twoview"),
        help="where pointmaps come from (default: synthetic for synthetic "
        "sources, rgbd when the source has depth; twoview: RGB only, classical geometry)",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key, e.g. tracking.Q_conf=2.0",
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="process at most N frames")
    p.add_argument(
        "--baseline",
        action="store_true",
        help="also run OpenCV RGB-D odometry on the same frames (needs depth)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    p.add_argument("--skip-bad-frames", action="store_true",
                   help="skip unreadable frames (listed in summary.json) instead of exit 2")  # fmt: skip
    _register_exports(p)
    p.set_defaults(func=run)


def _register_exports(p: argparse.ArgumentParser) -> None:
    """The options of ``mslam.export`` (docs/outputs.md); every path lies inside --out."""
    p.add_argument(
        "--rerun",
        metavar="FILE.rrd",
        help="record the run for the Rerun viewer "
        "(a file inside --out, e.g. OUT/run.rrd; needs the rerun extra)",
    )
    p.add_argument(
        "--rerun-spawn",
        action="store_true",
        help="also stream the run to a Rerun viewer (when a display is available)",
    )
    p.add_argument("--colmap", metavar="DIR", help="write a COLMAP model into DIR (inside --out)")
    p.add_argument(
        "--colmap-images",
        choices=("keyframes", "frames"),
        default="keyframes",
        help="COLMAP images: the keyframes (default) or every posed frame",
    )
    p.add_argument(
        "--depth",
        action="store_true",
        help="write a depth map of every posed frame into OUT/depth/",
    )


def run(args: argparse.Namespace) -> int:
    """Handler of ``mslam run`` (:func:`mslam.api.run` and a printed summary); the exit code."""
    from mslam.api import run as run_api
    from mslam.export import ExportRequest
    from mslam.outdir import check_target

    out = check_target(args.out, args.overwrite)
    result = run_api(
        args.source,
        out,
        config=args.config,
        prior=args.prior,
        calib=args.calib,
        kernels=args.kernels,
        precision=args.precision,
        device=args.device,
        max_frames=args.max_frames,
        settings=args.overrides,
        overwrite=args.overwrite,
        progress=not args.quiet,
        skip_bad_frames=args.skip_bad_frames,
        baseline=args.baseline,
        exports=ExportRequest.from_args(out, args),
    )
    if not args.quiet:
        _print_summary(result.summary, out)
    return 130 if result.interrupted else 0


def _print_summary(s: dict, out: Path) -> None:
    frames, posed = s["frames"], s["frames_with_pose"]
    lines = [
        f"mslam run: {s['source']} ({s['prior']} prior, {s['kernels']} kernels"
        f"{', calibrated' if s['calibrated'] else ''})",
        f"  POSED {posed} of {frames} frames ({100 * s['frames_posed_fraction']:.1f}%); "
        f"lost {s['lost_frames']}, skipped {s['skipped_frames']}",
    ]
    if s["lost_spans"]:
        spans = ", ".join(f"{a}-{b}" if a != b else f"{a}" for a, b in s["lost_spans"][:8])
        more = f" (+{len(s['lost_spans']) - 8} more)" if len(s["lost_spans"]) > 8 else ""
        lines.append(f"  lost spans (frame indices): {spans}{more}")
    focal = s.get("focal_estimate")
    if focal:
        lines.append(
            f"  focal length {focal['guess_px'] * focal['scale']:.1f} px: {focal['reason']}"
        )
        if focal.get("lens"):
            lines.append(f"  lens: {focal['lens']['reason']}")
    if s.get("depth_scale_assumed"):
        lines.append(
            f"  depth: {s['depth_scale_assumed']:g} raw units per metre assumed (the TUM layout's "
            "convention); a camera that stores millimetres needs depth_scale: 1000 in --calib"
        )
    if s.get("frames_posed_by_rotation"):
        lines.append(
            f"  {s['frames_posed_by_rotation']} frames posed by rotation alone "
            "(no parallax: at their keyframe's centre, no depth of their own)"
        )
    reloc = ", ".join(str(i) for i in s["relocalised_at"][:8])
    lines += [
        f"  relocalisations {s['relocalisations']} of {s['reloc_attempts']} attempts"
        f"{' at frames ' + reloc if reloc else ''}",
        f"  keyframes {s['keyframes']}, edges {s['edges']}: "
        f"{s['edges'] - s['loop_closure_edges']} between consecutive keyframes or from "
        f"relocalisation, {s['loop_closure_edges']} between non-consecutive keyframes found by "
        f"retrieval and verified (loop-closure candidates; {s.get('loop_closure_candidates_unverified', 0)} refused)",
        f"  {s['seconds']:.1f} s, {s['frames_per_second'] or 0:.2f} frames/s",
    ]
    if "ate_rmse" in s:
        lines.append(
            f"  ATE (Sim(3)) {s['ate_rmse']:.4f} m over {s['ate_frames']} of {frames} frames "
            f"= {s['ate_percent_of_path']:.2f}% of the {s['path_length']:.2f} m path "
            f"(scale {s['ate']['scale']:.3f})"
        )
    for seg in s.get("ate_by_map") or []:  # several maps: each segment aligned on its own
        ate = "not computed" if seg["ate_rmse"] is None else f"{seg['ate_rmse']:.4f} m"
        maps = ("maps " if len(seg["maps"]) > 1 else "map ") + ", ".join(map(str, seg["maps"]))
        lines.append(f"  {maps} on their own: ATE {ate} ({seg['frames']} posed frames)")
    if s.get("baseline") and s["baseline"].get("ate_rmse") is not None:
        lines.append(
            f"  RGB-D odometry baseline ATE {s['baseline']['ate_rmse']:.4f} m "
            "(baseline_odometry.txt)"
        )
    if s.get("evaluation_error"):
        lines.append(f"  {s['evaluation_error']}")
    for w in s["warnings"]:
        lines.append(f"  WARNING: {w}")
    for c in s.get("cautions", []):
        lines.append(f"  caution: {c}")
    if not s["warnings"]:
        lines.append(f"  plausible: no warning ({_checked(s)})")
    if s.get("interrupted"):
        lines.append("  interrupted: outputs contain the frames processed so far")
    lines.append(f"  outputs in {out}/")
    print("\n".join(lines), file=sys.stderr)


def _checked(s: dict) -> str:
    """What the plausibility checks covered in this run (``mslam.system.health``)."""
    if "ate_rmse" not in s:
        why = "ATE not computed" if s.get("evaluation_error") else "no ground truth"
        return f"posed fraction checked; scale and accuracy not checked: {why}"
    if not s.get("prior_metric"):
        return f"posed fraction checked; scale not checked: the {s['prior']} prior is not metric"
    return "posed fraction and aligned scale within limits"
