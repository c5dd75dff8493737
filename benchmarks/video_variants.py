"""Variants of a 7-Scenes clip for testing RGB-only SLAM on video nobody tuned to.

Writes TUM-layout folders (``rgb.txt``, ``groundtruth.txt``, ``calib.yaml``; no depth, so
every prior but ``twoview`` refuses them) whose images are symbolic links to the clip's
colour images in another order, with fresh timestamps at 30 Hz:

* ``fwd`` — the clip as it is;
* ``rev`` — played backwards;
* ``every2`` — every second frame (twice the motion per frame);
* ``every3``, ``every4`` — every third, every fourth frame (fast motion: three and four times
  the baseline and rotation between frames, as in a hand-held video at 10 or 7.5 Hz);
* ``every3rev`` — every third frame, played backwards;
* ``pingpong`` — forward then backward (``2N - 1`` frames, a closed loop);
* ``crop`` — the central 480x360 pixels of each image, written as PNG (other field of view
  and resolution; ``calib.yaml`` shifted accordingly);

and long sequences (revisits of the same room, for keyframe growth, loop closure, the backend's
cost as the map grows, memory and drift):

* ``pingpong2`` — forward, back, forward, back (``4N - 3`` frames; 597 for the 150-frame clip);
* ``loop3`` — three forward-and-back round trips (``6N - 5`` frames; 895);
* ``mixed`` — six passes alternating direction at strides 1, 2, 1, 3, 2, 1 (faster motion on
  the strided passes; 650 frames).

``--depth`` also writes ``NAME-depth``: the same frames with the clip's depth images linked
(``associations.txt``), for the RGB-D prior on the same order.

Usage: ``python benchmarks/video_variants.py OUT_DIR [--clip FOLDER] [--only NAME ...]``.
Each variant then runs as ``mslam run OUT_DIR/NAME --prior twoview --out RUN`` (``--calib
OUT_DIR/NAME/calib.yaml`` for the calibrated run); ``--table RUN ...`` prints one row per run
(posed share, ATE, keyframes, loop-closure edges, seconds per stage, warnings).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from mslam.datasets.readers import matrix_to_T_WC, natsorted, read_pose_matrix

CLIP = Path(__file__).resolve().parents[2] / "shared/data/seq/7scenes_redkitchen_f000000-000149"

#: Frame period of the written timestamps (s).
DT = 1.0 / 30.0

#: Size of the ``crop`` variant (pixels, centred).
CROP_WH = (480, 360)


def _orders(n: int) -> dict[str, list[int]]:
    """Frame orders of the variants that only reorder the clip's images."""
    return {
        "fwd": list(range(n)),
        "rev": list(range(n - 1, -1, -1)),
        "every2": list(range(0, n, 2)),
        "every3": list(range(0, n, 3)),
        "every4": list(range(0, n, 4)),
        "every3rev": list(range(n - 1, -1, -3)),
        "pingpong": list(range(n)) + list(range(n - 2, -1, -1)),
        "pingpong2": _passes(n, [1, 1, 1, 1]),
        "loop3": _passes(n, [1] * 6),
        "mixed": _passes(n, [1, 2, 1, 3, 2, 1]),
    }


def _passes(n: int, strides: list[int]) -> list[int]:
    """Frame order of passes over ``0..n-1`` alternating direction (first forward), pass ``p``
    taking every ``strides[p]``-th frame; a pass does not repeat the frame the last one ended
    on, and every pass reaches the clip's end it runs towards."""
    order = [0]
    for p, s in enumerate(strides):
        ahead = list(range(0, n, s)) if p % 2 == 0 else list(range(n - 1, -1, -s))
        if ahead[-1] != (n - 1 if p % 2 == 0 else 0):
            ahead.append(n - 1 if p % 2 == 0 else 0)
        order += [i for i in ahead if i != order[-1]]
    return order


def _pose_line(path: Path) -> str:
    """``tx ty tz qx qy qz qw`` of a 7-Scenes 4x4 camera-to-world pose file."""
    T = matrix_to_T_WC(read_pose_matrix(path))
    return " ".join(f"{v:.9f}" for v in T[:7])


def write_variant(clip: Path, out: Path, name: str, depth: bool = False) -> Path:
    """Write variant ``name`` of ``clip`` into ``out / name`` (``out / NAME-depth`` with the
    depth images linked when ``depth``); returns that folder."""
    rgb = natsorted(clip.glob("frame-*.color.*"))
    order = _orders(len(rgb)).get(name, list(range(len(rgb))))
    dst = out / (f"{name}-depth" if depth else name)
    (dst / "rgb").mkdir(parents=True, exist_ok=True)
    fx, fy, cx, cy = 585.0, 585.0, 320.0, 240.0
    rgb_lines, gt_lines, assoc_lines = [], [], []
    for k, i in enumerate(order):
        src = rgb[i]
        stem = src.name.split(".color.")[0]
        t = k * DT
        if name == "crop":
            img = cv2.imread(str(src))
            H, W = img.shape[:2]
            x0, y0 = (W - CROP_WH[0]) // 2, (H - CROP_WH[1]) // 2
            link = dst / "rgb" / f"{k:06d}.png"
            cv2.imwrite(str(link), img[y0 : y0 + CROP_WH[1], x0 : x0 + CROP_WH[0]])
        else:
            link = dst / "rgb" / f"{k:06d}{src.suffix}"
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(src.resolve())
        rgb_lines.append(f"{t:.6f} rgb/{link.name}")
        if depth:
            assoc_lines.append(
                f"{t:.6f} rgb/{link.name} {t:.6f} " + _link_depth(clip, dst, stem, k)
            )
        gt_lines.append(f"{t:.6f} " + _pose_line(clip / f"{stem}.pose.txt"))
    w, h = (640, 480)
    if name == "crop":
        cx, cy = cx - (w - CROP_WH[0]) // 2, cy - (h - CROP_WH[1]) // 2
        w, h = CROP_WH
    (dst / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (dst / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    if depth:
        (dst / "associations.txt").write_text("\n".join(assoc_lines) + "\n")
    (dst / "calib.yaml").write_text(
        f"width: {w}\nheight: {h}\ncalibration: {[fx, fy, cx, cy]}\ndepth_scale: 1000.0\n"
    )
    return dst


def _link_depth(clip: Path, dst: Path, stem: str, k: int) -> str:
    """Link the clip's depth image of ``stem`` as ``depth/k.png``; returns its relative path."""
    (dst / "depth").mkdir(exist_ok=True)
    link = dst / "depth" / f"{k:06d}.png"
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to((clip / f"{stem}.depth.png").resolve())
    return f"depth/{link.name}"


def read_summary(run: Path) -> dict[str, object]:
    """A run's ``summary.json`` with two figures added for tables: ``posed_pct`` (frames
    posed, %) and ``ate_cm`` (the ATE RMSE in cm as text, ``-`` without ground truth)."""
    import json

    s = json.loads((run / "summary.json").read_text())
    ate = s.get("ate_rmse")
    posed_pct = 100 * s["frames_posed_fraction"]
    return {**s, "posed_pct": posed_pct, "ate_cm": "-" if ate is None else f"{100 * ate:.2f}"}


def spread_text(s: dict) -> str:
    """The spread watch's events of a summary, for a table cell: ``caution ×2.17 (frame 333,
    up to ×3.1)`` per event (``runaway`` for one that made the run implausible), or ``–``."""
    cells = []
    for e in s.get("divergence_events", []):
        if e.get("kind") == "spread":
            more = (
                f", up to ×{e['largest_factor']:.3g}" if e["largest_factor"] > e["factor"] else ""
            )
            cells.append(f"{e['severity']} ×{e['factor']:.3g} (frame {e['frame']}{more})")
    return "; ".join(cells) or "–"


def table_row(run: Path) -> str:
    """One line of a run's ``summary.json``."""
    s = read_summary(run)
    stages = " ".join(f"{k}={v:.0f}" for k, v in s["stage_seconds"].items())
    return (
        f"{run.name}: posed {s['posed_pct']:.1f} %, ATE {s['ate_cm']} cm, "
        f"{s['keyframes']} keyframes, "
        f"{s['loop_closure_edges']} loop edges, {s['seconds']:.0f} s ({stages}), "
        f"plausible {s['plausible']}, warnings {s['warnings']}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, nargs="?")
    ap.add_argument("--table", type=Path, nargs="*", default=None)
    ap.add_argument("--clip", type=Path, default=CLIP)
    ap.add_argument("--only", nargs="*", default=["fwd", "rev", "every2", "pingpong", "crop"])
    ap.add_argument("--depth", action="store_true", help="also write NAME-depth (depth linked)")
    args = ap.parse_args(argv)
    if args.table is not None:
        for run in args.table:
            print(table_row(run))
        return 0
    if args.out is None:
        print("OUT_DIR: required unless --table", file=sys.stderr)
        return 2
    if not args.clip.is_dir():
        print(f"{args.clip}: clip folder not found", file=sys.stderr)
        return 2
    for name in args.only:
        print(write_variant(args.clip, args.out, name))
        if args.depth and name != "crop":
            print(write_variant(args.clip, args.out, name, depth=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
