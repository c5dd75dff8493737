"""docs/upstream.md §10.3 — loaders for 7-Scenes folders, EuRoC, plain image folders and video files.

* 7-Scenes: ``frame-XXXXXX.color.{png,jpg}`` (natsorted), ``frame-XXXXXX.depth.png``
  (millimetres, depth scale 1000), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world ground truth).
  Intrinsics from ``calib``, else ``calib.yaml``, else ``camera-intrinsics.txt``, else upstream's
  fx = fy = 585, cx = 320, cy = 240. Timestamps: the frame number parsed from the file name
  over the nominal 30 Hz (``frame-000400`` → 13.3333 s), so a clip keeps the dataset's own clock
  and associates with its own ground truth (upstream uses the position in the folder).
* EuRoC: ``mav0/cam0/data.csv`` (``timestamp_ns, filename``) and ``mav0/cam0/sensor.yaml``
  (``intrinsics: [fu, fv, cu, cv]``, ``distortion_coefficients``, ``resolution``); grey images
  become 3-channel; images are always undistorted (upstream ``always_undistort``); ground truth
  from ``state_groundtruth_estimate0/data.csv`` composed with the camera extrinsics ``T_BS``.
* Image folder: natsorted ``*.png``/``*.jpg``/``*.jpeg``, timestamps ``index / 30``.
* Video: ``cv2.VideoCapture``, timestamps ``index / fps``.

Public names, in reading order:
    load_7scenes, load_euroc, load_image_folder, VideoSequence, VIDEO_SUFFIXES
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from mslam.datasets.files import FileSequence, apply_calibration
from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.readers import (
    Calibration,
    matrix_to_T_WC,
    natsorted,
    read_calibration,
    read_pose_matrix,
    read_text_rows,
)
from mslam_ref import sim3, so3

__all__ = ["VIDEO_SUFFIXES", "VideoSequence", "load_7scenes", "load_euroc", "load_image_folder"]

#: File suffixes treated as videos (case-insensitive).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

#: Largest skip forward in a video that :class:`VideoSequence` decodes through instead of
#: seeking. The focal and lens pre-passes read frame pairs a few frames apart (53 of 58 seeks
#: on a 150-frame video skipped 1-7 frames); at 1920x1080 (MPEG-4 Part 2) a seek cost 63 ms
#: and a decoded frame 3 ms (2026-11-29).
GRAB_AHEAD = 16


def _seven_scenes_calib(folder: Path, shape: tuple[int, int]) -> Calibration:
    if (folder / "calib.yaml").is_file():
        return read_calibration(folder / "calib.yaml")
    H, W = shape
    K = np.array([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
    path = folder / "camera-intrinsics.txt"
    if path.is_file():
        try:
            K = np.loadtxt(path).reshape(3, 3)
        except ValueError:
            raise ValueError(f"{path}: expected a 3x3 intrinsics matrix") from None
    return Calibration(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2], (), 1000.0)


def load_7scenes(folder, calib=None, size=None) -> FileSequence:
    """Load a 7-Scenes sequence folder (module docstring)."""
    folder = Path(folder)
    rgb = natsorted(p for p in folder.glob("frame-*.color.*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if not rgb:
        raise ValueError(f"{folder}: no frame-XXXXXX.color.png/jpg images")
    stem = [p.name.split(".color.")[0] for p in rgb]
    depth = [folder / f"{s}.depth.png" for s in stem]
    has_depth = all(p.is_file() for p in depth)
    if not has_depth and any(p.is_file() for p in depth):
        missing = next(p for p in depth if not p.is_file())
        raise FileNotFoundError(f"{missing}: depth image missing")
    poses = [folder / f"{s}.pose.txt" for s in stem]
    T_WC = [matrix_to_T_WC(read_pose_matrix(p)) if p.is_file() else None for p in poses]
    cal = apply_calibration(calib)
    if cal is None:
        from mslam.datasets.readers import read_rgb

        cal = _seven_scenes_calib(folder, read_rgb(rgb[0]).shape[:2])
    if has_depth and cal.colour is None and cal.colour_auto is None:
        # 7-Scenes stores the Kinect's colour and depth unregistered (docs/priors.md).
        cal = replace(cal, colour_auto=True)
    # The dataset's own clock: the frame number of the file name at the nominal 30 Hz, so a clip
    # starting at frame-000400 keeps stamps 13.333... and associates with its own ground truth.
    try:
        numbers = [int(s.split("-")[-1]) for s in stem]
    except ValueError:
        raise ValueError(f"{folder}: expected frame-<number>.color.* file names") from None
    stamps = np.asarray(numbers, np.float64) / 30.0
    return FileSequence(
        folder.name, rgb, stamps, depth if has_depth else None, T_WC, cal, 1000.0, size
    )


def _read_yaml(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    text = "\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("%"))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not a valid YAML file ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping")
    return data


def _euroc_root(folder: Path) -> Path:
    for cand in (folder / "mav0", folder):
        if (cand / "cam0" / "data.csv").is_file():
            return cand
    raise FileNotFoundError(f"{folder / 'mav0/cam0/data.csv'}: EuRoC index not found")


def load_euroc(folder, calib=None, size=None) -> FileSequence:
    """Load a EuRoC MAV sequence (module docstring)."""
    root = _euroc_root(Path(folder))
    cam = root / "cam0"
    rows = read_text_rows(cam / "data.csv", 2)
    try:
        t_ns = np.array([int(r[0]) for r in rows], dtype=np.int64)
    except ValueError:
        raise ValueError(f"{cam / 'data.csv'}: non-integer timestamp") from None
    rgb = [cam / "data" / r[1] for r in rows]
    sensor = _read_yaml(cam / "sensor.yaml")
    missing = [k for k in ("intrinsics", "resolution") if k not in sensor]
    if missing:
        raise ValueError(f"{cam / 'sensor.yaml'}: missing key(s) {', '.join(missing)}")
    cal = apply_calibration(calib)
    if cal is None:
        fu, fv, cu, cv = (float(v) for v in sensor["intrinsics"])
        W, H = (int(v) for v in sensor["resolution"])
        dist = tuple(float(v) for v in sensor.get("distortion_coefficients", ()))
        cal = Calibration(W, H, fu, fv, cu, cv, dist, None)
    T_BS = np.eye(4)
    if isinstance(sensor.get("T_BS"), dict) and "data" in sensor["T_BS"]:
        T_BS = np.asarray(sensor["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
    T_WC = None
    gt_path = root / "state_groundtruth_estimate0" / "data.csv"
    if gt_path.is_file():
        g = np.array([[float(x) for x in r[:8]] for r in read_text_rows(gt_path, 8)])
        q_xyzw = g[:, [5, 6, 7, 4]]  # file order is w, x, y, z
        T_WB = np.concatenate([g[:, 1:4], so3.normalize(q_xyzw), np.ones((len(g), 1))], 1)
        T_bs = matrix_to_T_WC(T_BS)
        order = np.argsort(g[:, 0])
        k = np.clip(np.searchsorted(g[order, 0], t_ns), 0, len(g) - 1)
        idx = order[k]
        ok = np.abs(g[idx, 0] - t_ns) <= 5e6
        T_WC = [sim3.mul(T_WB[i], T_bs) if o else None for i, o in zip(idx, ok)]
    stamps = t_ns * 1e-9
    return FileSequence("euroc:" + root.parent.name, rgb, stamps, None, T_WC, cal, 5000.0, size)


def load_image_folder(folder, calib=None, size=None) -> FileSequence:
    """Load a folder of images (natsorted ``*.png``/``*.jpg``), timestamps ``index / 30``."""
    folder = Path(folder)
    imgs = natsorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if not imgs:
        raise ValueError(f"{folder}: no *.png or *.jpg images found")
    stamps = np.arange(len(imgs)) / 30.0
    return FileSequence(
        folder.name, imgs, stamps, None, None, apply_calibration(calib), 5000.0, size
    )


class VideoSequence(FrameSequence):
    """Frames of a video file via ``cv2.VideoCapture`` (upstream MP4Dataset; docs/upstream.md §10.3).

    Timestamps are ``k / fps`` for the k-th decoded frame; with ``subsample = s`` frame i is
    video frame ``i · s``. Frames are decoded sequentially; a skip of up to ``GRAB_AHEAD``
    frames forward decodes through them, other random access seeks.
    """

    def __init__(self, path, calib=None, subsample: int = 1, size=None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: video file not found")
        if int(subsample) < 1:
            raise ValueError(f"subsample: must be >= 1, got {subsample}")
        self.name = self.path.name
        self.stride = int(subsample)
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise ValueError(f"{self.path}: cannot open video")
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and np.isfinite(fps) and fps > 0 else 30.0
        n = 0
        while cap.grab():
            n += 1
        cap.release()
        if n == 0:
            raise ValueError(f"{self.path}: no decodable frames")
        k = np.arange(0, n, self.stride)
        self.timestamps = k / self.fps
        self._files = FileSequence(self.name, [self.path] * len(k), self.timestamps, None, None,
                                   apply_calibration(calib), 5000.0, size)  # fmt: skip
        self.K = self._files.K
        self.distortion = self._files.distortion
        self.has_depth = False
        self.T_WC = None
        self._cap: cv2.VideoCapture | None = None
        self._next = 0

    def _load(self, i: int) -> Frame:
        pos = i * self.stride
        if self._cap is not None and 0 < pos - self._next <= GRAB_AHEAD:
            for _ in range(pos - self._next):  # a short skip forward: decode, do not seek
                self._cap.grab()
        elif self._cap is None or pos != self._next:
            if self._cap is None:
                self._cap = cv2.VideoCapture(str(self.path))
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, pos)
        ok, bgr = self._cap.read()
        for _ in range(self.stride - 1):
            self._cap.grab()
        self._next = pos + self.stride
        if not ok or bgr is None:
            raise ValueError(f"{self.path}: cannot decode frame {pos}")
        return self._files._process(i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), None)
