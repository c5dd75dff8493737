"""Harder variants of a 7-Scenes clip: the ways real phone-like videos differ from it.

Writes TUM-layout folders (``rgb.txt``, ``groundtruth.txt``; no depth, so only the ``twoview``
prior accepts them) whose images are the clip's colour images changed in one way each:

* ``exposure`` — brightness gain swinging between 1/2 and 2 (one stop each way) over 60 frames;
* ``blur`` — a horizontal motion-blur kernel of 15 pixels (at 640x480) on every frame;
* ``jpeg`` — every frame re-encoded as JPEG at quality 8 (blocking, ringing);
* ``portrait`` — every frame rotated 90 degrees clockwise (480x640, a phone held upright);
* ``mirror`` — every frame mirrored left-right (ground truth reflected accordingly);
* ``static`` — the first frame repeated 20 times before the clip (a camera at rest);
* ``pause`` — frame 75 repeated 20 times (a camera that stops in the middle);
* ``dup`` — every 4th frame shown twice (a 24 Hz video converted to 30 Hz);
* ``dark`` — frames 70-84 nearly black with sensor noise (a covered lens, a light going out);
* ``cut`` — frames 0-74, then 149 back to 75 (the video cuts to the other end of the walk and
  comes back over it);
* ``away`` — frames 0-74, then 24 frames of somewhere else (the procedural room of
  ``synthetic:loop``, rendered at 160x120 and enlarged), then frames 75-149: the camera turns
  to another place for almost a second and comes back (no ground truth for the 24 frames);
* ``walker`` — a textured 200x360 block (a frame of the ``away`` insert) sliding across the
  image from left to right over frames 40-109 (someone walking through the view);
* ``drops`` — frames 50-53 and 100-104 left out (a video dropping frames);
* ``res320`` — every frame at 320x240;
* ``wide`` — the central 640x360 pixels (16:9);
* ``phone`` — ``static``, ``portrait``, ``exposure``, ``blur`` and ``jpeg`` at once;
* ``noise8``, ``noise15`` — Gaussian sensor noise of 8 and 15 grey levels per channel (fixed
  seed per frame; a low-light phone or a noisy webcam);
* ``gray`` — every frame converted to grey and written as three equal channels;
* ``every3noise8`` — every third frame with the noise of ``noise8`` (fast motion and noise);
* ``noise15lo`` — Gaussian noise of 15 grey levels per pixel of a 160x120 image (constant over
  4x4 blocks at 640x480): the noise of ``noise15`` at the resolution the two-view prior works
  at, where area downsampling no longer averages it down to a quarter;
* ``noise30lo`` — the same with 30 grey levels (a very noisy sensor at the working resolution);
* ``lowlight`` — a quarter of the exposure and the noise of ``noise8``, also per 4x4 block (a
  dim room filmed by a phone);
* ``video`` — the clip as an MPEG-4 video file ``video/clip.mp4`` (the video loader; no
  ground truth).

Ground truth follows each change: a mirrored image is the image of the mirrored world
(camera-to-world ``F M F``, ``F = diag(-1, 1, 1, 1)``), a rotated image that of the camera
turned about its optical axis (``M Rz^T``). Synthetic sources need no files: run
``synthetic:forward:120:160x120`` (a camera walking steadily towards a wall) and others directly.

Usage: ``python benchmarks/hard_variants.py OUT_DIR [--clip FOLDER] [--only NAME ...]``, then
``mslam run OUT_DIR/NAME --prior twoview --out RUN`` (``OUT_DIR/video/clip.mp4`` for ``video``)
and ``python benchmarks/hard_variants.py --table RUN ...`` for one Markdown row per run
(posed share, ATE, keyframes, frames per second, plausible, maps and how many were merged,
warnings).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from mslam.datasets.readers import matrix_to_T_WC, natsorted, read_pose_matrix

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import seven_scenes
from video_variants import read_summary

#: Frame period of the written timestamps (s).
DT = 1.0 / 30.0
#: Frames of the ``static`` variant's rest at the start.
STATIC_FRAMES = 20
#: Frame where ``pause`` stops the camera for ``STATIC_FRAMES`` frames.
PAUSE_AT = 75
#: Frames left out by ``drops`` (two bursts of 4 and 5).
DROPPED = set(range(50, 54)) | set(range(100, 105))
#: Frames of ``dark`` that are nearly black.
DARK = range(70, 85)
#: ``away``: frames of somewhere else, inserted before clip frame ``AWAY_AT``.
AWAY_FRAMES, AWAY_AT = 24, 75
#: ``walker``: the frames the block crosses, and its size (width, height) at 640x480.
WALKER_FRAMES, WALKER_SIZE = range(40, 110), (200, 360)
#: Motion-blur length of ``blur`` (pixels at 640x480).
BLUR_PX = 15
#: JPEG quality of ``jpeg``.
JPEG_QUALITY = 8
#: Period of the exposure swing of ``exposure`` (frames).
EXPOSURE_PERIOD = 60
#: Standard deviation of the added Gaussian noise per variant (grey levels per channel).
NOISE_SIGMA = {
    "noise8": 8.0,
    "noise15": 15.0,
    "every3noise8": 8.0,
    "noise15lo": 15.0,
    "noise30lo": 30.0,
}
#: Side of the pixel blocks that share one noise value in ``noise15lo``, ``noise30lo`` and
#: ``lowlight``
#: (640x480 to the 160x120 working resolution).
NOISE_BLOCK = {"noise15lo": 4, "noise30lo": 4, "lowlight": 4}
#: Exposure gain of ``lowlight``.
LOWLIGHT_GAIN = 0.25
#: Frame stride of ``every3noise8``.
FAST_STRIDE = 3

NAMES = (
    "exposure",
    "blur",
    "jpeg",
    "portrait",
    "mirror",
    "static",
    "pause",
    "dup",
    "dark",
    "cut",
    "away",
    "walker",
    "drops",
    "res320",
    "wide",
    "phone",
    "noise8",
    "noise15",
    "gray",
    "every3noise8",
    "noise15lo",
    "noise30lo",
    "lowlight",
    "video",
)

F = np.diag([-1.0, 1.0, 1.0, 1.0])
#: Camera-frame rotation of a 90-degree clockwise image turn: ``x' = -y``, ``y' = x``.
RZ = np.array([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


#: The changes ``phone`` combines, in the order they are applied.
PHONE = ("exposure", "blur", "jpeg", "portrait")


def _order(name: str, n: int) -> list[int]:
    if name in ("static", "phone"):
        return [0] * STATIC_FRAMES + list(range(n))
    if name == "pause":
        return list(range(PAUSE_AT)) + [PAUSE_AT] * STATIC_FRAMES + list(range(PAUSE_AT, n))
    if name == "dup":
        return [i for i in range(n) for _ in range(2 if i % 4 == 3 else 1)]
    if name == "drops":
        return [i for i in range(n) if i not in DROPPED]
    if name == "cut":
        return list(range(n // 2)) + list(range(n - 1, n // 2 - 1, -1))
    if name == "away":  # negative: the away frames, -1 first
        return (
            list(range(AWAY_AT)) + list(range(-1, -AWAY_FRAMES - 1, -1)) + list(range(AWAY_AT, n))
        )
    if name == "every3noise8":
        return list(range(0, n, FAST_STRIDE))
    return list(range(n))


def _image_op(name: str, k: int) -> Callable[[np.ndarray], np.ndarray]:
    """The change applied to the ``k``-th written image (BGR uint8 in and out)."""
    if name == "phone":
        ops = [_image_op(m, k) for m in PHONE]

        def phone(im: np.ndarray) -> np.ndarray:
            for op in ops:
                im = op(im)
            return im

        return phone
    if name == "exposure":
        gain = 2.0 ** np.sin(2 * np.pi * k / EXPOSURE_PERIOD)
        return lambda im: np.clip(im.astype(np.float32) * gain, 0, 255).astype(np.uint8)
    if name == "dark" and k in DARK:
        rng = np.random.default_rng(k)
        return lambda im: np.clip(rng.normal(4.0, 2.0, im.shape), 0, 255).astype(np.uint8)
    if name == "blur":
        kern = np.full((1, BLUR_PX), 1.0 / BLUR_PX, np.float32)
        return lambda im: cv2.filter2D(im, -1, kern, borderType=cv2.BORDER_REFLECT)
    if name == "jpeg":

        def jpeg(im: np.ndarray) -> np.ndarray:
            _ok, buf = cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            return cv2.imdecode(buf, cv2.IMREAD_COLOR)

        return jpeg
    if name == "lowlight":
        noise = _noise(8.0, NOISE_BLOCK[name], k)
        return lambda im: noise((im.astype(np.float32) * LOWLIGHT_GAIN).astype(np.uint8))
    if name in NOISE_SIGMA:
        return _noise(NOISE_SIGMA[name], NOISE_BLOCK.get(name, 1), k)
    if name == "walker" and k in WALKER_FRAMES:
        return lambda im: _walker(im, k)
    if name == "gray":
        return lambda im: cv2.cvtColor(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    if name == "portrait":
        return lambda im: cv2.rotate(im, cv2.ROTATE_90_CLOCKWISE)
    if name == "mirror":
        return lambda im: im[:, ::-1].copy()
    if name == "res320":
        return lambda im: cv2.resize(im, (320, 240), interpolation=cv2.INTER_AREA)
    if name == "wide":
        return lambda im: im[(im.shape[0] - 360) // 2 :][:360]
    return lambda im: im


def _noise(sigma: float, block: int, k: int) -> Callable[[np.ndarray], np.ndarray]:
    """Add Gaussian noise of ``sigma`` grey levels per channel, one value per ``block`` x
    ``block`` pixels, seeded by the written image's number ``k``."""
    rng = np.random.default_rng(k)

    def noisy(im: np.ndarray) -> np.ndarray:
        H, W, ch = im.shape
        n = rng.normal(0.0, sigma, (-(-H // block), -(-W // block), ch)).astype(np.float32)
        n = np.repeat(np.repeat(n, block, axis=0), block, axis=1)[:H, :W]
        return np.clip(np.rint(im.astype(np.float32) + n), 0, 255).astype(np.uint8)

    return noisy


def _pose(name: str, M: np.ndarray) -> np.ndarray:
    """Ground-truth camera-to-world 4x4 ``M`` of the changed image."""
    if name == "mirror":
        return F @ M @ F
    if name in ("portrait", "phone"):
        return M @ RZ.T
    return M


def write_variant(clip: Path, out: Path, name: str) -> Path:
    """Write variant ``name`` of ``clip`` into ``out / name``; returns the folder (the video
    file for ``video``)."""
    rgb = natsorted(clip.glob("frame-*.color.*"))
    dst = out / name
    (dst / "rgb").mkdir(parents=True, exist_ok=True)
    if name == "video":
        first = cv2.imread(str(rgb[0]))
        H, W = first.shape[:2]
        path = dst / "clip.mp4"
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (W, H))
        for src in rgb:
            vw.write(cv2.imread(str(src)))
        vw.release()
        return path
    rgb_lines, gt_lines = [], []
    for k, i in enumerate(_order(name, len(rgb))):
        file = dst / "rgb" / f"{k:06d}.png"
        t = k * DT
        if i < 0:  # somewhere else: no ground truth
            cv2.imwrite(str(file), _away_image(-1 - i, cv2.imread(str(rgb[0])).shape))
            rgb_lines.append(f"{t:.6f} rgb/{file.name}")
            continue
        src = rgb[i]
        img = _image_op(name, k)(cv2.imread(str(src)))
        cv2.imwrite(str(file), img)
        stem = src.name.split(".color.")[0]
        T = matrix_to_T_WC(_pose(name, read_pose_matrix(clip / f"{stem}.pose.txt")))
        rgb_lines.append(f"{t:.6f} rgb/{file.name}")
        gt_lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in T[:7]))
    (dst / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (dst / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return dst


def _away_image(j: int, shape: tuple[int, ...]) -> np.ndarray:
    """Frame ``j`` of the ``away`` insert: ``synthetic:loop`` (96 frames, 160x120), enlarged to
    the clip's ``shape`` (BGR uint8)."""
    from mslam.datasets.synthetic import make_sequence

    rgb = make_sequence("loop", n_frames=96, width=160, height=120)[j].rgb
    big = cv2.resize(rgb, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return cv2.cvtColor(big, cv2.COLOR_RGB2BGR)


def _walker(im: np.ndarray, k: int) -> np.ndarray:
    """``im`` with the ``walker`` block at its place in written frame ``k``: it enters at the
    left edge at the first of :data:`WALKER_FRAMES` and leaves at the right after the last."""
    H, W = im.shape[:2]
    w, h = (round(v * W / 640) for v in WALKER_SIZE)
    block = cv2.resize(_away_image(30, im.shape), (w, h), interpolation=cv2.INTER_AREA)
    t = (k - WALKER_FRAMES.start) / (len(WALKER_FRAMES) - 1)
    x0, y0 = round(-w + t * (W + w)), H - h
    a, b = max(x0, 0), min(x0 + w, W)
    out = im.copy()
    if b > a:
        out[y0:, a:b] = block[:, a - x0 : b - x0]
    return out


def maps_text(summary: dict) -> str:
    """A run's maps for a table: their number, and how many were merged (``2 (1 merged)``)."""
    merged = sum(m.get("merged") is not None for m in summary["maps"])
    return f"{len(summary['maps'])}" + (f" ({merged} merged)" if merged else "")


def table_row(run: Path) -> str:
    """One Markdown row of a run's ``summary.json``."""
    s = read_summary(run)
    return (
        f"| {run.name} | {s['frames']} | {s['posed_pct']:.1f} | {s['ate_cm']} | "
        f"{s['keyframes']} | "
        f"{s['frames_per_second']:.2f} | {s['plausible']} | {maps_text(s)} | "
        f"{'; '.join(s['warnings']) or '-'} |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("out", type=Path, nargs="?")
    ap.add_argument("--table", type=Path, nargs="*", default=None, help="runs to tabulate")
    ap.add_argument("--clip", type=Path, default=None, help="default: the shared 7-Scenes clip")
    ap.add_argument("--only", nargs="*", default=list(NAMES), choices=NAMES)
    args = ap.parse_args(argv)
    if args.table is not None:
        print(
            "| run | frames | posed % | ATE cm | keyframes | frames/s | plausible | maps | warnings |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for run in args.table:
            print(table_row(run))
        return 0
    if args.out is None:
        print("OUT_DIR: required unless --table", file=sys.stderr)
        return 2
    clip = args.clip or seven_scenes()
    if not clip.is_dir():
        print(f"{clip}: clip folder not found", file=sys.stderr)
        return 2
    for name in args.only:
        print(write_variant(clip, args.out, name))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
