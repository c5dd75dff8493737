"""Real videos nobody tuned to: public excerpts turned into TUM folders, run RGB only, tabulated.

The scoreboard (``scoreboard.py``) varies one 7-Scenes clip. This script checks the RGB-only
path on other cameras, scenes and motions, from sample data that public repositories carry
(none of it is in this repository; clone them yourself, use them for validation only):

* ``--yacynte DIR``: a clone of github.com/Yacynte/Monocular-Visual-Odometry (no licence
  file: all rights reserved). ``data/Tello_dataset/line``: a DJI Tello drone, 211 frames at
  960x720 and ~11 Hz, OptiTrack ground truth (take-off, 2.8 m straight ahead, landing).
  ``data/Kitti_dataset/{c-curve,line}``: two 51-frame KITTI odometry excerpts (10 Hz, grey),
  a curve and a straight road, with KITTI's poses.
* ``--benchun DIR``: a clone of github.com/benchun123/cuboid_slam_with_bbox_constraints.
  ``data/raw_imgs``: 58 key frames of TUM RGB-D fr3_cabinet, about 0.67 s apart (2-17° and
  7-23 cm between frames), with their ground-truth poses.
* ``--realsense DIR``: a clone of github.com/Taeyoung96/Make-ORB-SLAM2-RGBD-dataset: 193
  frames of an office with monitors from a hand-held Intel RealSense D435 at 640x480 and 30 Hz
  (turns, a loop back to the start, motion blur), depth in millimetres, no ground truth and no
  saved intrinsics (RESULTS.md calls it the D435 desk sequence). Its "ground truth" here is the RGB-D run of the same frames (``mslam run``
  with the D435's nominal intrinsics, 615 px, and ``depth_scale: 1000``): the RGB-only rows
  measure agreement with the RGB-D prior, not accuracy.
* ``--tum DIR`` (repeatable): any TUM RGB-D folder as downloaded (``rgb.txt``,
  ``groundtruth.txt``); calibrated runs use the Freiburg intrinsics its name gives.

Each excerpt becomes a TUM folder in ``WORK/inputs`` (images linked, not copied; timestamps
and ground truth as in the source; ``NAME.yaml`` beside it holds the intrinsics), and with
``--variants`` also played backwards and at every 2nd frame. Every folder is run with ``mslam
run SOURCE --prior twoview`` uncalibrated and calibrated, ``--jobs`` at a time, and each run's
``summary.json`` becomes a table row: frames posed, ATE and its share of the path, keyframes,
frames per second, the verdict and its warnings.

The Tello's poses are the Motive rigid body's (Euler X-Y-Z in degrees, Y up); the camera is
taken to look along the body's forward axis (``R_WC = R_WB diag(-1, -1, 1)``; positions are
the fair measure). KITTI's intrinsics come from its odometry calibration by image size (the
``line`` folder's ``calib.txt`` is the drone's).

Usage: ``python benchmarks/real_videos.py WORK [--yacynte DIR] [--benchun DIR] [--realsense DIR]
[--tum DIR ...]
[--variants] [--jobs 2] [--no-write] [--reuse]``; ``--reuse`` keeps the runs that already
have a ``summary.json`` (a table after a change that moves no trajectory); writes the section ``real-videos`` of RESULTS.md
unless ``--no-write``. About 20 min with the first three sources and ``--variants`` on 2 cores
(2026-11-29); the RealSense office adds about 9 min, its RGB-D reference run included
(2026-11-30).
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import video_variants
from _results import git_rev, table, write_section
from scipy.spatial.transform import Rotation
from scoreboard import run_one

from mslam.datasets.readers import calibration_yaml, read_calibration

#: KITTI odometry camera 0 by image size: fx, fy, cx, cy (sequences 00-02 and 13-21; 03;
#: 04-12), from the dataset's published calibration.
KITTI_INTRINSICS = {
    (1241, 376): [718.856, 718.856, 607.1928, 185.2157],
    (1242, 375): [721.5377, 721.5377, 609.5593, 172.854],
    (1226, 370): [707.0912, 707.0912, 601.8873, 183.1104],
}
#: TUM RGB-D Freiburg 3 colour camera (fx, fy, cx, cy; its images come undistorted).
FREIBURG3 = [535.4, 539.2, 320.1, 247.6]
#: Nominal fx, fy, cx, cy of a RealSense D435's colour stream at 640x480 (the recording kept
#: none of its own).
D435_640 = [615.0, 615.0, 320.0, 240.0]
#: Body (Y up, Z forward) to camera (x right, y down, z forward) of the drone.
R_BODY_CAMERA = np.diag([-1.0, -1.0, 1.0])

HEADER = ["input", "run", "frames", "posed %", "ATE", "% of path", "keyframes", "frames/s",
          "plausible", "spread watch", "warnings"]  # fmt: skip

Frames = list[tuple[float, Path]]
Poses = list[tuple[float, np.ndarray]]


def write_tum(folder: Path, frames: Frames, poses: Poses, calib: tuple[int, int, list[float]],
              note: str) -> Path:  # fmt: skip
    """A TUM folder: ``rgb/`` links, ``rgb.txt``, ``groundtruth.txt`` (``poses``: time, (4, 4)
    camera-to-world) and the intrinsics in ``folder.with_suffix(".yaml")``."""
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    lines = [f"# color images: {note}", "# timestamp filename"]
    for t, src in frames:
        link = folder / "rgb" / src.name
        if not link.exists():
            link.symlink_to(src.resolve())
        lines.append(f"{t:.6f} rgb/{src.name}")
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    gt = [f"# ground truth: {note}; camera-to-world", "# timestamp tx ty tz qx qy qz qw"]
    for t, T in poses:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        gt.append(f"{t:.6f} " + " ".join(f"{v:.7f}" for v in (*T[:3, 3], *q)))
    (folder / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    w, h, vals = calib
    folder.with_suffix(".yaml").write_text(calibration_yaml(_K(vals), w, h))
    return folder


def _K(vals: list[float]) -> np.ndarray:
    """(3, 3) intrinsics from ``[fx, fy, cx, cy]``."""
    fx, fy, cx, cy = vals
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot read the image")
    return img.shape[1], img.shape[0]


def tello(repo: Path, out: Path) -> Path:
    """The drone video (module docstring) as a TUM folder."""
    src = repo / "data" / "Tello_dataset" / "line"
    with open(src / "imu.csv") as f:
        rows = list(csv.reader(f))[1:]
    frames = [(float(r[1]), src / "images" / (r[0].strip("/") + ".png")) for r in rows]
    poses: Poses = []
    with open(src / "ground_truth.csv") as f:
        for i, r in enumerate(csv.reader(f)):
            v = r[1:8]
            if i < 7 or "" in v:
                continue
            t, rx, ry, rz, x, y, z = map(float, v)
            R = Rotation.from_euler("XYZ", [rx, ry, rz], degrees=True).as_matrix()
            poses.append((t, _pose(R @ R_BODY_CAMERA, np.array([x, y, z]))))
    K = [float(v) for v in (src / "calib.txt").read_text().split()[:12]]
    calib = (*_image_size(frames[0][1]), [K[0], K[5], K[2], K[6]])
    return write_tum(out / "tello", frames, poses, calib, "Tello line, Yacynte/Monocular-VO")


def kitti(repo: Path, out: Path, name: str) -> Path:
    """A KITTI excerpt (``c-curve`` or ``line``) as a TUM folder, 10 Hz timestamps."""
    src = repo / "data" / "Kitti_dataset" / name
    images = sorted((src / "images").glob("*.png"))
    A = np.loadtxt(src / "ground_truth.txt").reshape(-1, 3, 4)
    frames = [(0.1 * k, p) for k, p in enumerate(images)]
    poses = [(0.1 * k, _pose(A[k, :, :3], A[k, :, 3])) for k in range(min(len(A), len(images)))]
    size = _image_size(images[0])
    if size not in KITTI_INTRINSICS:
        raise ValueError(f"{src}: image size {size} is not a KITTI odometry camera's")
    folder = out / f"kitti_{name.replace('-', '')}"
    return write_tum(folder, frames, poses, (*size, KITTI_INTRINSICS[size]), f"KITTI {name}")


def cabinet(repo: Path, out: Path) -> Path:
    """fr3_cabinet's key frames (module docstring) as a TUM folder."""
    G = np.loadtxt(repo / "data" / "truth_cam_poses.txt")
    images = sorted((repo / "data" / "raw_imgs").glob("*.jpg"))
    if len(G) != len(images):
        raise ValueError(f"{repo}: {len(images)} images but {len(G)} poses")
    frames = [(t, p) for t, p in zip(G[:, 0], images, strict=True)]
    poses = [(g[0], _pose(Rotation.from_quat(g[4:8]).as_matrix(), g[1:4])) for g in G]
    calib = (*_image_size(images[0]), FREIBURG3)
    return write_tum(out / "fr3_cabinet_kf", frames, poses, calib, "TUM fr3_cabinet key frames")


def realsense(repo: Path, work: Path, reuse: bool) -> Path:
    """The RealSense office (module docstring) as a TUM folder; its poses are the RGB-D run's."""
    rows = [r.split() for r in (repo / "associations.txt").read_text().splitlines()
            if r.strip() and not r.startswith("#")]  # fmt: skip
    cal = work / "realsense_d435_mm.yaml"
    cal.write_text(calibration_yaml(_K(D435_640), 640, 480, depth_scale=1000.0))
    ref = work / "runs" / "realsense_office_rgbd"
    if not (reuse and (ref / "trajectory.txt").is_file()):
        ref = run_one(work, ref.name, [str(repo), "--calib", str(cal)], prior="rgbd")
    T = np.loadtxt(ref / "trajectory.txt")  # every frame, in frame order
    if len(T) != len(rows):
        raise ValueError(f"{ref}: the RGB-D reference posed {len(T)} of {len(rows)} frames")
    frames = [(k / 30.0, repo / r[1]) for k, r in enumerate(rows)]  # its own stamps are broken
    poses = [(k / 30.0, _pose(Rotation.from_quat(T[k, 4:8]).as_matrix(), T[k, 1:4]))
             for k in range(len(rows))]  # fmt: skip
    note = "RealSense D435 office, Taeyoung96/Make-ORB-SLAM2-RGBD-dataset; poses: the RGB-D run"
    return write_tum(
        work / "inputs" / "realsense_office", frames, poses, (640, 480, D435_640), note
    )


def variant(folder: Path, name: str, order: list[int]) -> Path:
    """``folder`` replayed in ``order`` (frame indices) with its first timestamps and steps;
    each frame keeps its true pose (re-stamped)."""
    rows = [ln.split() for ln in (folder / "rgb.txt").read_text().splitlines() if ln[:1] != "#"]
    gt = np.loadtxt(folder / "groundtruth.txt")
    stamps = np.array([float(r[0]) for r in rows])
    step = float(np.median(np.diff(stamps)))
    frames: Frames = []
    poses: Poses = []
    for k, i in enumerate(order):
        t = stamps[0] + k * step
        frames.append((t, folder / rows[i][1]))
        g = gt[np.argmin(np.abs(gt[:, 0] - stamps[i]))]
        poses.append((t, _pose(Rotation.from_quat(g[4:8]).as_matrix(), g[1:4])))
    c = read_calibration(folder.with_suffix(".yaml"))
    out = folder.parent / f"{folder.name}_{name}"
    calib = (c.width, c.height, [c.fx, c.fy, c.cx, c.cy])
    return write_tum(out, frames, poses, calib, f"{folder.name}, {name}")


def with_variants(folder: Path) -> list[Path]:
    """The folder, played backwards and at every 2nd frame."""
    n = sum(1 for ln in (folder / "rgb.txt").read_text().splitlines() if ln[:1] != "#")
    return [folder, variant(folder, "backwards", list(range(n))[::-1]),
            variant(folder, "every2", list(range(0, n, 2)))]  # fmt: skip


def row(name: str, mode: str, run: Path) -> list[object]:
    """One table row from a run's ``summary.json`` (a failed run: its error's first line)."""
    if not (run / "summary.json").exists():
        err = run.parent / f"{run.name}.err"
        why = err.read_text().strip().splitlines()[0] if err.exists() else "no summary.json"
        return [name, mode, "–", "–", "–", "–", "–", "–", "failed", "–", why[:80]]
    s = video_variants.read_summary(run)
    ate = s.get("ate_rmse")
    ate_text = "–" if ate is None else (f"{100 * ate:.2f} cm" if ate < 1 else f"{ate:.2f} m")
    pct = s.get("ate_percent_of_path")
    warnings = "; ".join(w[:60] for w in s["warnings"]) or "–"
    return [name, mode, s["frames"], f"{s['posed_pct']:.1f}", ate_text,
            "–" if pct is None else f"{pct:.1f}", s["keyframes"],
            f"{s['frames_per_second']:.2f}", s["plausible"], video_variants.spread_text(s),
            warnings]  # fmt: skip


def build(args: argparse.Namespace) -> list[Path]:
    """Every input folder the arguments name (the excerpts converted into ``WORK/inputs``)."""
    out = args.work / "inputs"
    makers: list[Callable[[], Path]] = []
    if args.yacynte:
        makers += [lambda: tello(args.yacynte, out), lambda: kitti(args.yacynte, out, "c-curve"),
                   lambda: kitti(args.yacynte, out, "line")]  # fmt: skip
    if args.benchun:
        makers.append(lambda: cabinet(args.benchun, out))
    if args.realsense:
        makers.append(lambda: realsense(args.realsense, args.work, args.reuse))
    folders = [make() for make in makers]
    if args.variants:
        folders = [v for f in folders for v in with_variants(f)]
    return folders + list(args.tum)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--yacynte", type=Path, help="clone of Yacynte/Monocular-Visual-Odometry")
    ap.add_argument("--benchun", type=Path, help="clone of cuboid_slam_with_bbox_constraints")
    ap.add_argument("--realsense", type=Path, help="clone of Make-ORB-SLAM2-RGBD-dataset")
    ap.add_argument("--tum", type=Path, action="append", default=[], help="a TUM RGB-D folder")
    ap.add_argument("--variants", action="store_true", help="also backwards and every 2nd")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--reuse", action="store_true",
                    help="keep runs that already have a summary.json in WORK/runs")  # fmt: skip
    args = ap.parse_args(argv)
    for opt in ("yacynte", "benchun", "realsense"):
        if getattr(args, opt) and not getattr(args, opt).is_dir():
            print(f"--{opt}: {getattr(args, opt)}: folder not found", file=sys.stderr)
            return 2
    for folder in args.tum:
        if not (folder / "rgb.txt").is_file():
            print(f"--tum: {folder}: no rgb.txt (not a TUM RGB-D folder)", file=sys.stderr)
            return 2
    if not (args.yacynte or args.benchun or args.realsense or args.tum):
        print("nothing to run: give --yacynte, --benchun, --realsense or --tum", file=sys.stderr)
        return 2
    jobs: dict[str, tuple[str, str, list[str]]] = {}
    for folder in build(args):
        yaml = folder.with_suffix(".yaml")
        jobs[folder.name] = (folder.name, "uncalibrated", [str(folder)])
        cal = ["--calib", str(yaml)] if yaml.is_file() else []
        jobs[f"{folder.name}_cal"] = (folder.name, "calibrated", [str(folder), *cal, "--set",
                                      "use_calib=true"])  # fmt: skip

    def run(key: str, argv: list[str]) -> Path:
        done = args.work / "runs" / key
        return done if args.reuse and (done / "summary.json").is_file() else run_one(
            args.work, key, argv)  # fmt: skip

    with ThreadPoolExecutor(args.jobs) as pool:
        runs = dict(zip(jobs, pool.map(lambda kv: run(kv[0], kv[1][2]), jobs.items())))
    rows = [row(name, mode, runs[key]) for key, (name, mode, _) in jobs.items()]
    body = (
        f"`python benchmarks/real_videos.py` at {git_rev()}: `mslam run SOURCE --prior twoview` "
        f"(RGB only, default settings, 160 px long side), uncalibrated and calibrated, on public "
        f"excerpts that are not in the repository (the script's docstring names them), "
        f"{'with their variants (backwards, every 2nd frame), ' if args.variants else ''}"
        f"{args.jobs} runs at a time.\n\n" + table(HEADER, rows)
    )
    if not args.no_write:
        write_section("real-videos", "Real videos nobody tuned to: the table", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
