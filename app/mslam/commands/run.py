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
folder beside ``--out`` and moved into place in one rename (``mslam.commands.outdir``); an
existing non-empty ``--out`` is refused unless ``--overwrite``. Ctrl-C stops at the next frame
boundary, writes a complete set marked ``"interrupted": true`` and exits 130; a second Ctrl-C
stops at once and leaves no output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mslam.commands import UserError

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
    p.set_defaults(func=run)


#: Longest image side the RGB-D prior may run at without asking (a whole frame costs ~0.2 s at
#: 160x120 and ~0.8 s at 512x384 on 2 cores, benchmarks/RESULTS.md; more at the full size).
RGBD_MAX_AUTO_SIDE = 320


def _check_resolution(source, cfg) -> None:
    """Refuse, before any work, to run the RGB-D prior at full resolution by accident."""
    if source.prior_name != "rgbd" or cfg.dataset.long_side:
        return
    H, W = source.sequence[0].shape
    if max(H, W) > RGBD_MAX_AUTO_SIDE:
        raise UserError(
            f"this config runs the RGB-D prior at the full {W}x{H} (dataset.long_side = 0), "
            "about a second per frame on 2 CPU cores; add --set dataset.long_side=160 (the rgbd "
            "config's working size), use --config rgbd_512 (the paper's 512 px), or "
            f"--set dataset.long_side={max(H, W)} to insist"
        )


def run(args: argparse.Namespace) -> int:
    """Handler of ``mslam run``; returns the exit code."""
    from mslam.commands.outdir import check_target, staged_folder
    from mslam.config import config_to_dict, load_config
    from mslam.kernels import load_kernels
    from mslam.system import open_source, run_slam, write_outputs

    out = check_target(args.out, args.overwrite)
    if args.source and Path(args.source).resolve().is_relative_to(out.resolve()):
        raise UserError(f"--out {out}: contains SOURCE {args.source}; choose another folder")
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f"--max-frames: must be >= 1, got {args.max_frames}")
    from mslam.device import use_device

    use_device(args.device, args.kernels, args.precision)  # before any work: no fallback
    overrides = [  # one switch: the kernels' arch and the network's torch device
        *args.overrides,
        f"local_opt.use_cuda={str(args.device == 'cuda').lower()}",
        f"mast3r_prior.device={args.device}",
    ]
    cfg = load_config(args.config, overrides)
    source = open_source(args.source, cfg, args.calib, args.prior, args.max_frames)
    if args.config is None and source.prior_name in ("rgbd", "twoview"):
        # The RGB-D prior's packaged default (configs/rgbd.yaml, docs/system.md): its working
        # resolution and two tracking keys differ from base.yaml, so open the source again.
        cfg = load_config(source.prior_name, overrides)
        source = open_source(args.source, cfg, args.calib, args.prior, args.max_frames)
    _check_resolution(source, cfg)
    if args.calib is not None and not cfg.use_calib:
        from dataclasses import replace

        cfg = replace(cfg, use_calib=True)  # upstream: --calib forces use_calib
    kernels = load_kernels(args.kernels)
    if args.baseline and not source.sequence.has_depth:
        raise UserError(f"--baseline: {source.name} has no depth images (the RGB-D odometry "
                        "baseline needs them)")  # fmt: skip
    system, meta = run_slam(
        source, cfg, kernels, progress=not args.quiet, skip_bad_frames=args.skip_bad_frames
    )
    if args.baseline and not meta["interrupted"]:
        from mslam.baselines import rgbd_odometry_ate

        meta["baseline"] = rgbd_odometry_ate(source.sequence)
    meta["config"] = config_to_dict(cfg)
    meta["device"] = args.device
    with staged_folder(out, args.overwrite) as tmp:
        summary = write_outputs(tmp, system, source.sequence, meta)
    if not args.quiet:
        _print_summary(summary, out)
    return 130 if meta["interrupted"] else 0


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
    reloc = ", ".join(str(i) for i in s["relocalised_at"][:8])
    lines += [
        f"  relocalisations {s['relocalisations']} of {s['reloc_attempts']} attempts"
        f"{' at frames ' + reloc if reloc else ''}",
        f"  keyframes {s['keyframes']}, edges {s['edges']} "
        f"(loop closure {s['loop_closure_edges']})",
        f"  {s['seconds']:.1f} s, {s['frames_per_second'] or 0:.2f} frames/s",
    ]
    if "ate_rmse" in s:
        lines.append(
            f"  ATE (Sim(3)) {s['ate_rmse']:.4f} m over {s['ate_frames']} of {frames} frames "
            f"= {s['ate_percent_of_path']:.2f}% of the {s['path_length']:.2f} m path "
            f"(scale {s['ate']['scale']:.3f})"
        )
    if s.get("baseline") and s["baseline"].get("ate_rmse") is not None:
        lines.append(
            f"  RGB-D odometry baseline ATE {s['baseline']['ate_rmse']:.4f} m "
            "(baseline_odometry.txt)"
        )
    if s.get("evaluation_error"):
        lines.append(f"  {s['evaluation_error']}")
    for w in s["warnings"]:
        lines.append(f"  WARNING: {w}")
    if not s["warnings"]:
        lines.append("  plausible: no warning (posed fraction and scale within limits)")
    if s.get("interrupted"):
        lines.append("  interrupted: outputs contain the frames processed so far")
    lines.append(f"  outputs in {out}/")
    print("\n".join(lines), file=sys.stderr)
