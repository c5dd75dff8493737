"""``mslam run`` — the SLAM system on a sequence, with outputs in ``--out DIR`` (spec §13).

::

    mslam run [SOURCE] --out DIR [--config FILE] [--kernels ref|fast] [--calib FILE]
              [--prior synthetic|rgbd|mast3r|twoview] [--set SECTION.KEY=VALUE ...]
              [--max-frames N] [--baseline] [--quiet]

SOURCE: nothing (the built-in synthetic ``loop``), ``synthetic:NAME[:FRAMES[:WxH]]``, a
TUM-layout folder, a 7-Scenes folder, an image folder or a video file. Everything that can be
checked is checked before the first frame (config keys, calibration, prior); a bad input is
one line on stderr, exit code 2, and no output file. Ctrl-C writes what exists and exits 130.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mslam_ref.commands import UserError

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
        help="YAML config (inherit: base.yaml); 'base', 'calib', 'rgbd' and 'twoview' name the "
        "packaged files (default: base, or the prior's own for rgbd and twoview)",
    )
    p.add_argument(
        "--kernels",
        choices=("ref", "fast"),
        default="fast",
        help="kernel set: NumPy reference or Taichi (default: fast)",
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
    p.set_defaults(func=run)


def _check_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is not a folder")
    parent = out if out.exists() else out.parent
    while not parent.exists():
        parent = parent.parent
    import os

    if not os.access(parent, os.W_OK):
        raise UserError(f"--out {out}: not writable")


def run(args: argparse.Namespace) -> int:
    """Handler of ``mslam run``; returns the exit code."""
    from mslam_ref.config import config_to_dict, load_config
    from mslam_ref.kernels import load_kernels
    from mslam_ref.system import open_source, run_slam, write_outputs

    out = Path(args.out)
    _check_out(out)
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f"--max-frames: must be >= 1, got {args.max_frames}")
    cfg = load_config(args.config, args.overrides)
    source = open_source(args.source, cfg, args.calib, args.prior, args.max_frames)
    if args.config is None and source.prior_name in ("rgbd", "twoview"):
        # The RGB-D prior's packaged default (configs/rgbd.yaml, docs/system.md): its working
        # resolution and two tracking keys differ from base.yaml, so open the source again.
        cfg = load_config(source.prior_name, args.overrides)
        source = open_source(args.source, cfg, args.calib, args.prior, args.max_frames)
    if args.calib is not None and not cfg.use_calib:
        from dataclasses import replace

        cfg = replace(cfg, use_calib=True)  # upstream: --calib forces use_calib
    kernels = load_kernels(args.kernels)
    baseline = None
    if args.baseline:
        if not source.sequence.has_depth:
            raise UserError("--baseline: the RGB-D odometry baseline needs depth images")
    system, meta = run_slam(source, cfg, kernels, progress=not args.quiet)
    if args.baseline and not meta["interrupted"]:
        from mslam_ref.baselines import rgbd_odometry_ate

        baseline = rgbd_odometry_ate(source.sequence)
        meta["baseline"] = baseline
    meta["config"] = config_to_dict(cfg)
    summary = write_outputs(out, system, source.sequence, meta)
    if not args.quiet:
        _print_summary(summary, out)
    return 130 if meta["interrupted"] else 0


def _print_summary(s: dict, out: Path) -> None:
    lines = [
        f"mslam run: {s['source']} ({s['prior']} prior, {s['kernels']} kernels"
        f"{', calibrated' if s['calibrated'] else ''})",
        f"  frames {s['frames']} (with pose {s['frames_with_pose']}, lost {s['lost_frames']}, "
        f"skipped {s['skipped_frames']}), keyframes {s['keyframes']}, edges {s['edges']} "
        f"(loop closure {s['loop_closure_edges']}), relocalisations {s['relocalisations']}",
        f"  {s['seconds']:.1f} s, {s['frames_per_second'] or 0:.2f} frames/s",
    ]
    if "ate_rmse" in s:
        lines.append(
            f"  ATE (Sim(3)) {s['ate_rmse']:.4f} m = {s['ate_percent_of_path']:.2f}% of the "
            f"{s['path_length']:.2f} m path (scale {s['ate']['scale']:.3f})"
        )
    if s.get("baseline") and s["baseline"].get("ate_rmse") is not None:
        lines.append(f"  RGB-D odometry baseline ATE {s['baseline']['ate_rmse']:.4f} m")
    if s.get("interrupted"):
        lines.append("  interrupted: outputs contain the frames processed so far")
    lines.append(f"  outputs in {out}/")
    print("\n".join(lines), file=sys.stderr)
