"""A pure pan rendered from one photo: homography warps of a still image, with ground truth.

A camera that turns about its centre sees the scene through ``u_src ~ K_src R K_out⁻¹ u_out``,
whatever the depths, so one photo gives a pure rotation with real texture at any field of view.
Writes a TUM-layout folder (``rgb/``, ``rgb.txt``, ``groundtruth.txt`` with the rotations about
a fixed centre, ``calib.yaml`` of the output camera) for ``mslam run DIR --prior twoview``::

    python benchmarks/pan_from_photo.py OUT [--image IMG] [--fov 46] [--frames 90] [--amp 6]

The default image is the first colour frame of the shared 7-Scenes clip (``MSLAM_DATA``); its
camera is taken as fx = fy = 525 px at 640x480. The yaw swings by ``±amp`` degrees, the pitch
by half and the roll by 0.3 of it; the output is 320x240 with ``--fov`` degrees across its
width, which must stay inside the photo's view.

Measured 2026-11-27 (RGB only, uncalibrated, default settings): ``--fov 46`` (a focal length
1.36 times the 60° guess) and ``--fov 56``: every frame posed at one centre, orientations
0.09° / 0.21° and 0.10° / 0.21° off (median / max), one keyframe (benchmarks/RESULTS.md).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

from mslam_ref import so3

W, H = 320, 240
F_SRC = 525.0  # the 7-Scenes colour camera, about (640x480)


def pan_rotations(n: int, amp_deg: float) -> np.ndarray:
    """(n, 4) unit quaternions of the pan: pitch, yaw and roll swinging about the centre."""
    s = np.arange(n) / n
    w = np.stack(
        [
            0.5 * amp_deg * np.sin(4 * np.pi * s),
            amp_deg * np.sin(2 * np.pi * s),
            0.3 * amp_deg * np.sin(6 * np.pi * s),
        ],
        -1,
    )
    return np.stack([so3.exp(np.radians(r)) for r in w])


def render_pan(photo: np.ndarray, q: np.ndarray, fov_deg: float) -> list[np.ndarray]:
    """The views (H, W, 3) of ``photo`` (its camera fx = fy = F_SRC, centred) turned by ``q``."""
    h, w = photo.shape[:2]
    K_src = np.array([[F_SRC, 0, (w - 1) / 2], [0, F_SRC, (h - 1) / 2], [0, 0, 1]])
    f = (W / 2) / np.tan(np.radians(fov_deg) / 2)
    K_out = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return [
        cv2.warpPerspective(
            photo, K_src @ so3.to_matrix(qk) @ np.linalg.inv(K_out), (W, H), flags=flags
        )
        for qk in q
    ]


def write_pan(out: Path, photo: np.ndarray, n: int, amp_deg: float, fov_deg: float) -> None:
    """Write the folder of the module docstring."""
    q = pan_rotations(n, amp_deg)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    rgb, gt = [], []
    for k, img in enumerate(render_pan(photo, q, fov_deg)):
        cv2.imwrite(str(out / "rgb" / f"{k:06d}.png"), img)
        rgb.append(f"{k / 30:.6f} rgb/{k:06d}.png")
        gt.append(f"{k / 30:.6f} 0 0 0 " + " ".join(f"{v:.9f}" for v in q[k]))
    (out / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (out / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    f = (W / 2) / np.tan(np.radians(fov_deg) / 2)
    c = f"[{f:.4f}, {f:.4f}, {(W - 1) / 2}, {(H - 1) / 2}]"
    (out / "calib.yaml").write_text(f"width: {W}\nheight: {H}\ncalibration: {c}\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--image", type=Path, default=None)
    ap.add_argument("--fov", type=float, default=46.0, help="output field of view, degrees")
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--amp", type=float, default=6.0, help="yaw amplitude, degrees")
    args = ap.parse_args(argv)
    image = args.image
    if image is None:
        data = Path(
            os.environ.get("MSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
        )
        image = data / "seq" / "7scenes_redkitchen_f000000-000149" / "frame-000000.color.jpg"
    photo = cv2.imread(str(image))
    if photo is None:
        print(f"{image}: not an image", file=sys.stderr)
        return 2
    if not 10.0 < args.fov < 120.0 or args.frames < 2:
        print("--fov: 10-120 degrees; --frames: at least 2", file=sys.stderr)
        return 2
    write_pan(args.out, photo, args.frames, args.amp, args.fov)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
