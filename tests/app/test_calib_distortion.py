"""``--calib`` with distortion terms: the run uses the intrinsics of the frames it reads.

A file source given a calibration with distortion undistorts every frame into the new camera
matrix ``K_opt`` (upstream's ``getOptimalNewCameraMatrix``, alpha 0, centred principal point;
``mslam.datasets.files``). The pointmaps and the calibrated solves must use that matrix, not the
file's ``K``: with TUM fr1's coefficients the two differ by 11 % in focal length and 16 px in the
principal point, and the calibrated runs on fr1_rpy turned and scaled wrongly
(benchmarks/RESULTS.md, "Depth measured in metres").
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mslam.config import load_config
from mslam.datasets.images import optimal_intrinsics
from mslam.system.sources import open_source

W, H = 64, 48
K_FILE = [60.0, 60.5, 31.0, 25.0]
#: TUM fr1's coefficients (k1, k2, p1, p2, k3): a lens whose undistortion moves the corners.
DIST = [0.262383, -0.953104, -0.005358, 0.002628, 1.163314]


def _tum_folder(root: Path, dist: list[float]) -> tuple[Path, Path]:
    """A 3-frame TUM-layout folder of textured images and a calibration YAML beside it."""
    rng = np.random.default_rng(0)
    (root / "rgb").mkdir(parents=True)
    lines = []
    for i in range(3):
        img = cv2.GaussianBlur(rng.integers(0, 255, (H, W, 3), dtype=np.uint8), (3, 3), 0)
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), img)
        lines.append(f"{i * 0.1:.1f} rgb/{i}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    calib = root.parent / f"{root.name}.yaml"
    values = ", ".join(str(v) for v in K_FILE + dist)
    calib.write_text(f"width: {W}\nheight: {H}\ncalibration: [{values}]\n")
    return root, calib


def test_a_distorted_calibration_runs_on_the_undistorted_frames_intrinsics(tmp_path):
    folder, calib = _tum_folder(tmp_path / "seq", DIST)
    src = open_source(str(folder), load_config("twoview"), calib, "twoview")
    fx, fy, cx, cy = K_FILE
    K_file = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    K_opt = optimal_intrinsics(K_file, np.array(DIST), W, H, True)
    assert src.K is not None and src.sequence.K is not None
    np.testing.assert_array_equal(src.K, K_opt)
    np.testing.assert_array_equal(src.sequence.K, K_opt)
    assert abs(K_opt[0, 0] / fx - 1) > 0.05  # the lens matters: not the file's K


def test_a_calibration_without_distortion_keeps_its_own_intrinsics(tmp_path):
    folder, calib = _tum_folder(tmp_path / "seq", [])
    src = open_source(str(folder), load_config("twoview"), calib, "twoview")
    fx, fy, cx, cy = K_FILE
    np.testing.assert_array_equal(src.K, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]))
