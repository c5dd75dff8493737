"""``mslam eval REFERENCE ESTIMATE`` — ATE of a trajectory file against ground truth (docs/upstream.md §12).

The argument order is evo's (``evo_ape tum REFERENCE ESTIMATE``): ground truth first.

Both files may be TUM (``timestamp tx ty tz qx qy qz qw``), KITTI (12 numbers per line) or an
EuRoC ground-truth csv; the format is detected from the content (``mslam.formats.read_trajectory``).
TUM/EuRoC pairs are associated by timestamp as evo does (nearest stamp within ``--max-diff``);
KITTI files have no stamps, so they are associated by index and need equal lengths (evo's
``kitti`` mode). Prints one JSON object: ``ate_rmse``, ``ate_mean``, ``ate_median``, ``ate_max``,
``scale``, ``matched``, ``n_est``, ``align``, ``max_diff``. A position coordinate beyond
:data:`MAX_ABS_COORDINATE` is refused (one line, exit 2).

Equivalent evo command: ``evo_ape tum REFERENCE ESTIMATE -as`` (``--align sim3``, the paper's
protocol), ``-a`` (``se3``) or no flag (``none``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mslam.commands import UserError, print_json

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``eval`` sub-command to the ``mslam`` parser."""
    p = subparsers.add_parser(
        "eval",
        help="ATE RMSE of a trajectory against ground truth (evo-compatible)",
        description="Absolute trajectory error (translation part) after Umeyama alignment, "
        "with evo's timestamp association. Prints JSON. Argument order as evo's "
        "'evo_ape tum REFERENCE ESTIMATE': the ground truth FIRST, then the estimate.",
    )
    p.add_argument(
        "groundtruth",
        type=Path,
        metavar="REFERENCE",
        help="ground-truth trajectory, first as in evo (TUM, KITTI or EuRoC csv)",
    )
    p.add_argument(
        "estimate", type=Path, metavar="ESTIMATE", help="estimated trajectory (same formats)"
    )
    p.add_argument(
        "--align",
        choices=("sim3", "se3", "none"),
        default="sim3",
        help="alignment before the error: sim3 (evo -as, default), se3 (evo -a) or none",
    )
    p.add_argument(
        "--max-diff",
        type=float,
        default=0.01,
        help="largest timestamp difference for a match, seconds (default 0.01, as evo)",
    )
    p.set_defaults(func=run)


#: Largest accepted |coordinate| of a position, in the file's units (metres: a million km).
#: Beyond it the numbers are not a camera path, and squared errors would overflow float64.
MAX_ABS_COORDINATE = 1e9


def _read(path: Path) -> tuple[Any, Any]:
    import numpy as np

    from mslam import formats as io

    if not path.is_file():
        raise UserError(f"{path}: no such file")
    try:
        stamps, poses = io.read_trajectory(path)
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text trajectory file") from None
    big = np.abs(poses[:, :3]) > MAX_ABS_COORDINATE
    if big.any():
        i, c = np.argwhere(big)[0]
        raise UserError(
            f"{path}: pose {i + 1} has coordinate {'xyz'[c]} = {poses[i, c]:g}, too large for a "
            f"trajectory (|coordinate| <= {MAX_ABS_COORDINATE:g})"
        )
    return stamps, poses


def run(args: argparse.Namespace) -> int:
    """Handler of ``mslam eval``: read both files, compute the ATE, print JSON; returns 0."""
    from mslam.evaluate import ate

    if not (args.max_diff >= 0):
        raise UserError(f"--max-diff: must be >= 0, got {args.max_diff}")
    gt_stamps, gt_poses = _read(args.groundtruth)
    est_stamps, est_poses = _read(args.estimate)
    if (est_stamps is None) != (gt_stamps is None):
        kitti = args.estimate if est_stamps is None else args.groundtruth
        raise UserError(
            f"{kitti}: KITTI poses have no timestamps; both files must be KITTI to associate by "
            "index"
        )
    try:
        res = ate(est_stamps, est_poses, gt_stamps, gt_poses, args.align, args.max_diff)
    except ValueError as exc:
        raise UserError(f"{args.groundtruth} (reference) vs {args.estimate}: {exc}") from None
    out = res.to_dict()
    out["align"] = args.align
    out["max_diff"] = args.max_diff if est_stamps is not None else None
    print_json(out)
    return 0
