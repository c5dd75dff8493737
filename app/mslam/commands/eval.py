"""``mslam eval REFERENCE ESTIMATE`` — ATE of a trajectory file against ground truth (docs/upstream.md §12).

The argument order is evo's (``evo_ape tum REFERENCE ESTIMATE``): ground truth first.

Both files may be TUM (``timestamp tx ty tz qx qy qz qw``), KITTI (12 numbers per line) or an
EuRoC ground-truth csv; the format is detected from the content (``mslam.formats.read_trajectory``).
TUM/EuRoC pairs are associated by timestamp as evo does (nearest stamp within ``--max-diff``);
KITTI files have no stamps, so they are associated by index and need equal lengths (evo's
``kitti`` mode). Prints one JSON object: ``ate_rmse``, ``ate_mean``, ``ate_median``, ``ate_max``,
``scale``, ``matched``, ``n_est``, ``align``, ``max_diff``, and where both files carry
orientations the rotation figures of :mod:`mslam.rotation_metrics` (``rotation_gain``: 1 when
the estimate turns as much as the camera, ``rotation_error_median_deg`` / ``_max_deg``: the
relative rotation error over ``rotation_lag_s``). A position coordinate beyond
:data:`MAX_ABS_COORDINATE` is refused (one line, exit 2).

Equivalent evo command: ``evo_ape tum REFERENCE ESTIMATE -as`` (``--align sim3``, the paper's
protocol), ``-a`` (``se3``) or no flag (``none``).

Dense map (paper Table 3, ``mslam.map_metrics``): ``--map PLY`` with ``--truth-cloud PLY`` or
``--truth-rgbd FOLDER`` adds a ``map`` object (accuracy, completion, chamfer, medians, far
fraction) and a ``map_alignment`` object to the JSON; the map is moved by the same alignment as
the trajectory, then with ``--map-icp`` registered onto the truth by ICP. REFERENCE may also be
an RGB-D folder (7-Scenes or TUM layout): its ground-truth poses are the reference.
"""

from __future__ import annotations

import argparse
import sys
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
    p.add_argument(
        "--map",
        type=Path,
        metavar="PLY",
        help="the run's reconstruction.ply: add dense-map metrics (needs a --truth-* option)",
    )
    truth = p.add_mutually_exclusive_group()
    truth.add_argument(
        "--truth-cloud",
        type=Path,
        metavar="PLY",
        help="true point cloud or mesh (PLY: binary or ASCII, colours optional), world frame",
    )
    truth.add_argument(
        "--truth-rgbd",
        type=Path,
        metavar="FOLDER",
        help="RGB-D folder with ground-truth poses (7-Scenes or TUM layout): the truth is the "
        "depth of every 5th frame in the estimate's time span, voxel-downsampled to 1 cm",
    )
    p.add_argument(
        "--map-poses",
        action="store_true",
        help="align the map by the Sim(3) that fits the cameras' positions and orientations "
        "(the trajectory alone leaves the rotation about a straight path's axis free)",
    )
    p.add_argument(
        "--map-icp",
        action="store_true",
        help="after the trajectory's alignment, register the map onto the truth by rigid ICP "
        "(the paper's 7-Scenes protocol; the trajectory's ATE is unchanged)",
    )
    p.set_defaults(func=run)


#: Largest accepted |coordinate| of a position, in the file's units (metres: a million km).
#: Beyond it the numbers are not a camera path, and squared errors would overflow float64.
MAX_ABS_COORDINATE = 1e9

#: Above this angle (degrees) between the trajectory's Sim(3) rotation and the one the cameras'
#: orientations imply, ``mslam eval --map`` notes on stderr that the map metrics measure the
#: alignment (docs/evaluation.md §4.1: 7.5–12° on the 7-Scenes clip's nearly straight path,
#: where even the true depth at the estimated poses scores a chamfer of 10–15 cm).
FREE_ROTATION_NOTE_DEG = 3.0


def _read(path: Path) -> tuple[Any, Any]:
    import numpy as np

    from mslam import formats as io

    if path.is_dir():
        _, stamps, poses = _open_rgbd(path, need_depth=False).ground_truth()
        return stamps, poses
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
    from mslam.rotation_metrics import rotation_report

    if not (args.max_diff >= 0):
        raise UserError(f"--max-diff: must be >= 0, got {args.max_diff}")
    if args.map is None and (args.truth_cloud or args.truth_rgbd or args.map_icp or args.map_poses):
        raise UserError(
            "--truth-cloud/--truth-rgbd/--map-icp/--map-poses: give the map with --map PLY"
        )
    if args.map_icp and args.map_poses:
        raise UserError("--map-icp and --map-poses: choose one alignment of the map")
    if args.map is not None and args.truth_cloud is None and args.truth_rgbd is None:
        raise UserError("--map: give the truth with --truth-cloud PLY or --truth-rgbd FOLDER")
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
    i, j = res.est_index, res.gt_index
    stamps = None if est_stamps is None else est_stamps[i]
    out = {**res.to_dict(), **(rotation_report(stamps, est_poses[i], gt_poses[j]) or {})}
    out["align"] = args.align
    out["max_diff"] = args.max_diff if est_stamps is not None else None
    if args.map is not None:
        out["map"], out["map_alignment"] = _map(args, (est_stamps, est_poses, gt_stamps, gt_poses))
        _note_free_rotation(out["map_alignment"])
    print_json(out)
    return 0


def _note_free_rotation(info: dict[str, Any]) -> None:
    """One line on stderr when the map's alignment is set by a rotation the path leaves free."""
    angle = info.get("rotation_vs_orientations_deg")
    if info.get("refine") == "none" and angle is not None and angle > FREE_ROTATION_NOTE_DEG:
        print(
            f"mslam eval: note: the trajectory's Sim(3) turns the map {angle:.1f}° away from the "
            "rotation the cameras' orientations imply (the positions leave it free on a nearly "
            "straight path), so the map metrics measure that alignment as much as the map; "
            "compare --map-poses or --map-icp",
            file=sys.stderr,
        )


def _open_rgbd(folder: Path, need_depth: bool = True) -> Any:
    """The sequence of an RGB-D folder, with ground truth (and depth when ``need_depth``)."""
    from mslam.datasets import load_sequence

    try:
        seq = load_sequence(folder)
    except (OSError, ValueError) as exc:
        raise UserError(f"{folder}: {exc}") from None
    if seq.ground_truth() is None:
        raise UserError(f"{folder}: no ground-truth pose for any frame")
    if need_depth and (seq.K is None or not seq.has_depth):
        raise UserError(f"{folder}: needs depth images and intrinsics for --truth-rgbd")
    return seq


def _truth(args: argparse.Namespace, est_stamps: Any) -> Any:
    from mslam import formats as io
    from mslam.map_metrics import truth_from_rgbd

    if args.truth_cloud is not None:
        if not args.truth_cloud.is_file():
            raise UserError(f"{args.truth_cloud}: no such file")
        try:
            return io.read_ply(args.truth_cloud)[0]
        except ValueError as exc:
            raise UserError(str(exc)) from None
    if not args.truth_rgbd.is_dir():
        raise UserError(f"{args.truth_rgbd}: no such folder")
    seq = _open_rgbd(args.truth_rgbd)
    span = None
    if est_stamps is not None and len(est_stamps):
        span = (float(min(est_stamps)) - args.max_diff, float(max(est_stamps)) + args.max_diff)
    try:
        return truth_from_rgbd(seq, t_range=span)
    except ValueError as exc:
        raise UserError(f"{args.truth_rgbd}: {exc}") from None


def _map(
    args: argparse.Namespace, trajs: tuple[Any, Any, Any, Any]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``--map``: read the map and the truth, align the map like the trajectory, score it."""
    from mslam import formats as io
    from mslam.map_metrics import evaluate_map

    if not args.map.is_file():
        raise UserError(f"{args.map}: no such file")
    try:
        xyz = io.read_ply(args.map)[0]
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if len(xyz) == 0:
        raise UserError(f"{args.map}: the map has no points")
    truth = _truth(args, trajs[0])
    refine = "icp" if args.map_icp else ("poses" if args.map_poses else "none")
    try:
        m, _, info = evaluate_map(xyz, *trajs, truth, args.align, args.max_diff, refine)
    except ValueError as exc:
        raise UserError(f"{args.map}: {exc}") from None
    return m.to_dict(), info
