"""``mslam synth NAME --out DIR`` — write a synthetic sequence in TUM layout.

Writes ``rgb/*.png``, ``depth/*.png`` (uint16, 5000 units per metre), ``rgb.txt``,
``depth.txt``, ``associations.txt``, ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``,
camera-to-world), ``calib.yaml`` (``width``, ``height``, ``calibration: [fx, fy, cx, cy]``,
``depth_scale``) and ``synth.json`` (name, seed, size, frames and, for the ``jump`` and
``detour`` paths, ``jump_indices``: the frames where the camera is relocated). All or nothing:
the whole set is written into a temporary folder beside ``--out`` and moved into place in one
rename (``mslam.outdir``); a non-empty ``--out`` is refused unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mslam.atomic import write_atomic
from mslam.commands import UserError, print_json

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``synth`` sub-command."""
    from mslam_ref.synthetic import PATHS

    p = subparsers.add_parser(
        "synth",
        help="write a synthetic RGB-D sequence with ground truth in TUM layout",
        description="Render a procedural room along a named camera path and write it in TUM "
        "layout (rgb/, depth/, rgb.txt, depth.txt, associations.txt, groundtruth.txt, "
        "calib.yaml).",
    )
    p.add_argument("name", help=f"camera path: {', '.join(PATHS)}")
    p.add_argument("--out", required=True, type=Path, help="output folder (new or empty)")
    p.add_argument("--frames", type=int, default=80, help="number of frames (default 80)")
    p.add_argument("--width", type=int, default=160, help="image width (default 160)")
    p.add_argument("--height", type=int, default=120, help="image height (default 120)")
    p.add_argument("--seed", type=int, default=0, help="scene and path seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Render and write the sequence; prints a JSON summary."""
    from mslam.datasets.synthetic import make_sequence
    from mslam.datasets.tum import write_tum_sequence
    from mslam.outdir import check_target, staged_folder
    from mslam_ref.synthetic import PATHS, check_synthetic_size, detour_indices, jump_indices

    name = args.name.removeprefix("synthetic:")
    if name not in PATHS:
        raise UserError(f"unknown synthetic path {args.name!r}; choose one of {', '.join(PATHS)}")
    if args.frames < 2:
        raise UserError(f"--frames must be >= 2, got {args.frames}")
    if not (8 <= args.width <= 4096 and 8 <= args.height <= 4096):
        raise UserError(f"--width/--height must be in [8, 4096], got {args.width}x{args.height}")
    check_synthetic_size(args.frames, args.width, args.height, "--frames/--width/--height")
    out = check_target(args.out, args.overwrite)
    seq = make_sequence(name, args.frames, args.width, args.height, args.seed)
    info = {
        "name": seq.name,
        "frames": len(seq),
        "width": args.width,
        "height": args.height,
        "seed": args.seed,
        "out": str(out),
        "calibration": [seq.K[0, 0], seq.K[1, 1], seq.K[0, 2], seq.K[1, 2]],
        "depth_scale": 5000.0,
    }
    teleports = {"jump": jump_indices, "detour": detour_indices}
    if name in teleports:
        info["jump_indices"] = list(teleports[name](len(seq)))
    with staged_folder(out, args.overwrite) as tmp:
        write_tum_sequence(seq, tmp, depth_scale=5000.0, overwrite=True)
        write_atomic(tmp / "synth.json", json.dumps(info, indent=2, allow_nan=False) + "\n")
    print_json(info)
    return 0
