"""Videos of a real room along new camera paths: the 7-Scenes clip re-rendered, with ground truth.

The clip's RGB-D frames, placed by their ground-truth poses, are one coloured point cloud of a
real kitchen. Rendering that cloud from other cameras gives videos with real texture, real
geometry and motions the clip does not have (a hand that wobbles, a sweep, a lens with another
field of view), each with exact poses. Every ``STRIDE``-th frame of the clip is read at 320x240
(colour resampled onto the depth camera's grid, ``mslam.datasets.registration``), and each new
view is drawn by a z-buffer at twice the output size (the nearest surface within 2 % of depth
wins, its samples averaged), holes filled from their neighbours, then area-downsampled.

Paths (``--path``): the clip's own positions, with its orientations turned by

* ``wobble``: a hand-held wobble, yaw ±7° and pitch ±4° at 0.9 and 1.4 Hz, roll ±2°;
* ``sweep``: a slow yaw sweep of ±14° over the clip with a pitch of ±3°;
* ``still``: nothing (the clip's own motion through the cloud: the renderer's own error);
* ``weave``: the clip's orientations, its positions moved off its nearly straight line
  (``WEAVE_CM``: one period across the path's second axis, one and a half along its third),
  so that the positions fix every axis of a trajectory's Sim(3) alignment (the clip's own
  spread is 27 / 7.4 / 1.0 cm; docs/evaluation.md §4.1).

``--fov`` sets the output's horizontal field of view (the depth camera sees 57°; wider views
show the border of what the clip saw, filled from its edge), ``--step`` plays every n-th pose
(faster motion), ``--k1`` bends the output through a radial lens: the pinhole view's pixel
``x_u`` (centred, divided by the 60° focal length of the output width, so one ``k1`` is the
same warp at every ``--fov``) is seen at ``x_d = x_u (1 + k1 |x_u|²)``; ``k1 < 0`` barrel,
``> 0`` pincushion, black where the pinhole view has no content unless ``--fill`` renders a
pinhole view large enough for every output pixel (as a real barrel lens sees more of the
scene), ``calib.yaml`` still the pinhole's (``mslam.priors.twoview_lens`` finds the lens).
``--depth`` also writes each view's depth (the z-buffer's nearest surface, 0 in holes;
``depth/``, ``depth.txt``, 5000 units per metre as TUM), for RGB-D runs and for
``mslam eval --map --truth-rgbd OUT``.
``--shutter R`` reads the rows out one after another, as a rolling shutter does: row ``y`` is
seen at the pose a fraction ``R · y / H`` of the way to the next played pose (``BANDS`` bands of
rows; the last frame all at once); the ground truth is the middle row's pose. Writes a
TUM-layout folder (``rgb/``, ``rgb.txt``, ``groundtruth.txt``, ``calib.yaml`` of the output
camera) for ``mslam run DIR --prior twoview``::

    python benchmarks/novel_views.py OUT --path wobble [--fov 50] [--step 1] [--size 320x240]
        [--k1 0 [--fill]] [--shutter 0] [--depth]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import add_data_argument, seven_scenes

from mslam.datasets import load_sequence
from mslam_ref import sim3

#: Every STRIDE-th frame of the clip goes into the cloud.
STRIDE = 3
#: Size at which the clip's frames are back-projected.
SRC_W, SRC_H = 320, 240
#: Samples within this relative depth of a pixel's nearest one are averaged into it.
Z_TOL = 0.02
PATHS = ("wobble", "sweep", "still", "weave")
#: Amplitudes [cm] of the ``weave`` path's offsets along the clip path's second and third axes.
WEAVE_CM = (15.0, 10.0)
#: Depth units per metre of ``--depth`` (TUM's).
DEPTH_SCALE = 5000.0
#: Bands of rows rendered at their own pose (``--shutter``).
BANDS = 8
#: Largest |k1| (beyond it a barrel lens folds the corners of a 4:3 frame back).
K1_MAX = 0.3


def room_cloud(seq) -> tuple[np.ndarray, np.ndarray]:
    """``(X_w (N, 3), rgb (N, 3) float)``: the clip's frames (a loaded 7-Scenes sequence)
    back-projected into the world."""
    seq.register_colour()
    K = seq.K.copy()
    K[:2] *= SRC_W / seq[0].shape[1]
    v, u = np.mgrid[0:SRC_H, 0:SRC_W].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    X_all, c_all = [], []
    for i in range(0, len(seq), STRIDE):
        f = seq[i]
        rgb = cv2.resize(f.rgb, (SRC_W, SRC_H), interpolation=cv2.INTER_AREA)
        z = cv2.resize(f.depth, (SRC_W, SRC_H), interpolation=cv2.INTER_NEAREST)
        ok = (z > 0.1) & (z < 6.0)
        X_c = rays[ok] * z[ok, None]
        X_all.append(sim3.act(np.asarray(f.T_WC), X_c))
        c_all.append(rgb[ok].astype(np.float64))
    return np.concatenate(X_all), np.concatenate(c_all)


def turn(path: str, n: int, step: int) -> np.ndarray:
    """(n, 3, 3) rotations (camera frame) added to the clip's orientations, at 30 frames/s."""
    t = np.arange(n) * step / 30.0
    T = max(t[-1], 1e-9)
    if path == "wobble":
        ang = np.stack([4 * np.sin(2 * np.pi * 1.4 * t), 7 * np.sin(2 * np.pi * 0.9 * t + 0.5),
                        2 * np.sin(2 * np.pi * 0.6 * t)], -1)  # fmt: skip
    elif path == "sweep":
        ang = np.stack([3 * np.sin(2 * np.pi * t / T), 14 * np.sin(2 * np.pi * t / T),
                        np.zeros_like(t)], -1)  # fmt: skip
    else:
        ang = np.zeros((n, 3))
    return Rotation.from_rotvec(np.radians(ang)).as_matrix()


def shift(path: str, centres: np.ndarray) -> np.ndarray:
    """(n, 3) camera centres of ``path``: the clip's ``centres`` (n, 3), for ``weave`` moved
    off their principal axis (module docstring)."""
    if path != "weave":
        return centres
    mean = centres.mean(0)
    _, _, Vt = np.linalg.svd(centres - mean, full_matrices=False)
    s = np.linspace(0.0, 1.0, len(centres))[:, None]
    a2, a3 = (a / 100.0 for a in WEAVE_CM)
    return centres + a2 * np.sin(2 * np.pi * s) * Vt[1] + a3 * np.sin(3 * np.pi * s) * Vt[2]


def zbuffer(X_w, T_WC: np.ndarray, K: np.ndarray, W: int, H: int):
    """The cloud's points (N, 3) seen from ``T_WC`` (4, 4) through ``K`` on a (W, H) grid:
    ``(sel, idx, z, zbuf)``, the indices into ``X_w`` of the points in front (beyond 5 cm) that
    land inside, their pixels ``v · W + u`` (nearest), depths, and the nearest depth per pixel
    (W · H,), ``inf`` where none lands."""
    T_CW = np.linalg.inv(T_WC)
    X = X_w @ T_CW[:3, :3].T + T_CW[:3, 3]
    sel = np.flatnonzero(X[:, 2] > 0.05)
    X = X[sel]
    z = X[:, 2]
    u = np.round(K[0, 0] * X[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * X[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    sel, idx, z = sel[inside], v[inside] * W + u[inside], z[inside]
    zbuf = np.full(W * H, np.inf)
    np.minimum.at(zbuf, idx, z)
    return sel, idx, z, zbuf


def render_depth(X_w, T_WC: np.ndarray, K: np.ndarray, W: int, H: int) -> np.ndarray:
    """(H, W) depth [m] of the cloud's nearest surface from ``T_WC`` (4, 4), 0 where no point
    falls (drawn at the output size)."""
    zbuf = zbuffer(X_w, T_WC, K, W, H)[3]
    return np.where(np.isfinite(zbuf), zbuf, 0.0).reshape(H, W)


def render(X_w, rgb, T_WC: np.ndarray, K: np.ndarray, W: int, H: int) -> np.ndarray:
    """(H, W, 3) uint8 view of the cloud from ``T_WC`` (4, 4), drawn at twice the size."""
    W2, H2 = 2 * W, 2 * H
    K2 = K.copy()
    K2[:2] *= 2.0
    K2[:2, 2] += 0.5  # pixel centres of the doubled grid
    sel, idx, z, zbuf = zbuffer(X_w, T_WC, K2, W2, H2)
    col = rgb[sel]
    keep = z <= zbuf[idx] * (1 + Z_TOL)
    acc = np.zeros((W2 * H2, 3))
    cnt = np.zeros(W2 * H2)
    np.add.at(acc, idx[keep], col[keep])
    np.add.at(cnt, idx[keep], 1.0)
    img = (acc / np.maximum(cnt, 1)[:, None]).reshape(H2, W2, 3)
    hole = (cnt == 0).reshape(H2, W2).astype(np.uint8)
    img = np.clip(img, 0, 255).astype(np.uint8)
    if hole.any():
        img = cv2.inpaint(img, hole, 3, cv2.INPAINT_TELEA)
    return cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)


def lens_maps(k1: float, W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 remap tables: for each pixel of the distorted output, its pinhole pixel
    (module docstring, ``--k1``; the lens inverted by fixed-point iteration)."""
    f = (W / 2) / np.tan(np.radians(30.0))
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    x, y = (u - (W - 1) / 2) / f, (v - (H - 1) / 2) / f
    xu, yu = x.copy(), y.copy()
    for _ in range(10):
        r2 = xu * xu + yu * yu
        xu, yu = x / (1 + k1 * r2), y / (1 + k1 * r2)
    return (xu * f + (W - 1) / 2).astype(np.float32), (yu * f + (H - 1) / 2).astype(np.float32)


def between(T0: np.ndarray, T1: np.ndarray, t: float) -> np.ndarray:
    """(4, 4) pose a fraction ``t`` of the way from ``T0`` to ``T1`` (rotation by slerp)."""
    rot = Rotation.from_matrix(T0[:3, :3]).inv() * Rotation.from_matrix(T1[:3, :3])
    T = T0.copy()
    T[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec(t * rot.as_rotvec()).as_matrix()
    T[:3, 3] = (1 - t) * T0[:3, 3] + t * T1[:3, 3]
    return T


def shutter_view(X_w, rgb, T0, T1, K, W, H, shutter: float) -> tuple[np.ndarray, np.ndarray]:
    """The (H, W, 3) view read out row band by row band from ``T0`` towards ``T1`` (module
    docstring, ``--shutter``; ``T1`` None: all at ``T0``), and the middle row's pose."""
    if T1 is None or not shutter:
        return render(X_w, rgb, T0, K, W, H), T0
    img = np.empty((H, W, 3), np.uint8)
    edges = np.linspace(0, H, BANDS + 1).round().astype(int)
    for a, b in itertools.pairwise(edges):
        img[a:b] = render(X_w, rgb, between(T0, T1, shutter * (a + b) / (2 * H)), K, W, H)[a:b]
    return img, between(T0, T1, shutter / 2)


def write_video(
    out: Path,
    clip: Path,
    path: str,
    fov_deg: float,
    step: int,
    size,
    k1: float = 0.0,
    fill: bool = False,
    shutter: float = 0.0,
    depth: bool = False,
) -> None:
    """Write the folder of the module docstring."""
    W, H = size
    maps = lens_maps(k1, W, H) if k1 else None
    pad = (0, 0)  # pinhole pixels rendered beyond each side (``--fill``)
    if maps is not None and fill:
        pad = tuple(int(np.ceil(max(-m.min(), m.max() - (n - 1), 0))) for m, n in zip(maps, (W, H)))
        maps = (maps[0] + pad[0], maps[1] + pad[1])
    seq = load_sequence(str(clip))
    X_w, rgb = room_cloud(seq)
    poses = [sim3.to_matrix(np.asarray(seq.T_WC[i])) for i in range(0, len(seq), step)]
    centres = shift(path, np.array([T[:3, 3] for T in poses]))
    for T, c in zip(poses, centres, strict=True):
        T[:3, 3] = c
    R_add = turn(path, len(poses), step)
    f = (W / 2) / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    if depth:
        (out / "depth").mkdir(exist_ok=True)
    lines, gt, dlines = [], [], []
    T_all = []
    for T, R in zip(poses, R_add, strict=True):
        T_all.append(T.copy())
        T_all[-1][:3, :3] = T[:3, :3] @ R
    K_pad = K.copy()
    K_pad[:2, 2] += pad
    for k, T0 in enumerate(T_all):
        T1 = T_all[k + 1] if k + 1 < len(T_all) else None
        img, T = shutter_view(X_w, rgb, T0, T1, K_pad, W + 2 * pad[0], H + 2 * pad[1], shutter)
        if maps is not None:
            img = cv2.remap(img, *maps, cv2.INTER_LINEAR)
        cv2.imwrite(str(out / "rgb" / f"{k:06d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        ts = f"{k * step / 30:.6f}"
        lines.append(f"{ts} rgb/{k:06d}.png")
        if depth:
            z = render_depth(X_w, T, K, W, H)
            raw = np.clip(np.round(z * DEPTH_SCALE), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(out / "depth" / f"{k:06d}.png"), raw)
            dlines.append(f"{ts} depth/{k:06d}.png")
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        gt.append(ts + " " + " ".join(f"{x:.9f}" for x in (*T[:3, 3], *q)))
    (out / "rgb.txt").write_text("\n".join(lines) + "\n")
    (out / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if depth:
        (out / "depth.txt").write_text("\n".join(dlines) + "\n")
    c = f"[{f:.4f}, {f:.4f}, {(W - 1) / 2}, {(H - 1) / 2}]"
    (out / "calib.yaml").write_text(f"width: {W}\nheight: {H}\ncalibration: {c}\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--path", choices=PATHS, default="wobble")
    ap.add_argument("--fov", type=float, default=50.0, help="horizontal field of view, degrees")
    ap.add_argument("--step", type=int, default=1, help="play every n-th pose")
    ap.add_argument("--size", default="320x240", help="WxH of the output")
    ap.add_argument("--k1", type=float, default=0.0, help="radial lens of the output (docstring)")
    ap.add_argument("--fill", action="store_true", help="no black corners (docstring)")
    ap.add_argument("--shutter", type=float, default=0.0, help="rolling-shutter readout, 0-1")
    ap.add_argument("--depth", action="store_true", help="also write depth (docstring)")
    add_data_argument(ap)
    args = ap.parse_args(argv)
    clip = seven_scenes(args.data)
    if not clip.is_dir():
        print(f"{clip}: the 7-Scenes clip is not there (--data or MSLAM_DATA)", file=sys.stderr)
        return 2
    try:
        size = tuple(int(x) for x in args.size.lower().split("x"))
        assert len(size) == 2 and min(size) >= 16
    except (ValueError, AssertionError):
        print(f"--size: expected WxH, got {args.size!r}", file=sys.stderr)
        return 2
    if (
        not 10.0 < args.fov < 120.0
        or args.step < 1
        or abs(args.k1) > K1_MAX
        or not 0 <= args.shutter <= 1
        or (args.depth and (args.k1 or args.shutter))
    ):
        print(f"--fov: 10-120 degrees; --step: at least 1; --k1: within ±{K1_MAX}; --shutter: 0-1;"
              " --depth: a pinhole view only (no --k1, --shutter)", file=sys.stderr)  # fmt: skip
        return 2
    opts = (args.k1, args.fill, args.shutter, args.depth)
    write_video(args.out, clip, args.path, args.fov, args.step, size, *opts)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
