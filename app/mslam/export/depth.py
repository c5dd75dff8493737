"""Per-frame depth maps rendered from the final map (``mslam run --depth``).

A posed frame ``f`` is tracked against keyframe ``k`` (``T_WC_f = T_WC_k ∘ T_CkCf``). Its depth
map is keyframe ``k``'s canonical pointmap seen from ``f``: the world points
``X_W = T_WC_k · X_canon`` (the PLY's points) are moved into the frame's camera with the rigid
part of its pose, ``X_f = R_f^T (X_W - t_f)`` (the pose written to ``trajectory.txt``, whose
Sim(3) scale is dropped), projected with the run's intrinsics (``mslam.export.camera``) and
z-buffered (nearest point per pixel). Depth is therefore in the map's world units, and
back-projecting a pixel with the intrinsics and the ``trajectory.txt`` pose lands on the PLY.
A pixel is confident when the point that won it has ``C / N > 1.5`` (the PLY's threshold).

Files in ``depth/`` (``NNNNNN`` = the frame index, six digits):

* ``NNNNNN.png`` — uint16 depth × 1000 (millimetres when the map is metric), 0 where no
  confident point landed;
* ``NNNNNN.npy`` — float32 (H, W) depth, 0 where no point landed;
* ``NNNNNN_conf.npy`` — float32 (H, W) average confidence of the point that won, 0 where none;
* ``frames.txt`` — ``index timestamp keyframe tx ty tz qx qy qz qw`` per frame;
* ``intrinsics.txt`` — ``width height fx fy cx cy`` (pixel-centre convention), after a
  ``#`` line saying whether they were given or estimated.

Public names, in reading order:
    render_depth, write_depth_maps
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mslam.atomic import write_atomic
from mslam.system.frontend import SlamSystem
from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray

__all__ = ["render_depth", "write_depth_maps"]

#: Average-confidence threshold of a confident pixel (the PLY's).
C_CONF_THRESHOLD = 1.5
#: Depth scale of the PNG files: stored value = depth × this (millimetres for metres).
PNG_DEPTH_SCALE = 1000.0


def render_depth(
    X_W: FloatArray, C: FloatArray, T_WC: FloatArray, K: FloatArray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer world points into a camera.

    Args:
        X_W: (N, 3) world points.
        C: (N,) their average confidences.
        T_WC: (8,) Sim(3) camera-to-world; its scale is ignored (rigid pose).
        K: (3, 3) intrinsics, pixel-centre convention.
        shape: (H, W) of the depth map.

    Returns:
        depth (H, W) float32 (0 where no point lands) and confidence (H, W) float32 of the
        nearest point per pixel (0 where none).
    """
    H, W = shape
    T = np.asarray(T_WC, np.float64)
    R = so3.to_matrix(T[3:7])
    Xc = (np.asarray(X_W, np.float64) - T[:3]) @ R  # R^T (X - t), row vectors
    z = Xc[:, 2]
    ok = np.isfinite(z) & (z > 1e-9)
    zs = np.where(ok, z, 1.0)
    u = np.rint(K[0, 0] * Xc[:, 0] / zs + K[0, 2])
    v = np.rint(K[1, 1] * Xc[:, 1] / zs + K[1, 2])
    ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
    pix = (v[ok] * W + u[ok]).astype(np.int64)
    zk, ck = z[ok], np.asarray(C, np.float64)[ok]
    order = np.argsort(-zk, kind="stable")  # far to near: the nearest write wins
    depth = np.zeros(H * W, np.float32)
    conf = np.zeros(H * W, np.float32)
    depth[pix[order]] = zk[order]
    conf[pix[order]] = ck[order]
    return depth.reshape(H, W), conf.reshape(H, W)


def _frame_rows(system: SlamSystem) -> list[tuple[int, float, int, FloatArray]]:
    """(index, timestamp, keyframe, T_WC (8,)) of every posed frame, final keyframe poses."""
    T_kf = system.keyframes.poses()
    rows = []
    for p in system.poses:
        if 0 <= p.kf < len(system.keyframes):
            rows.append(
                (int(p.index), float(p.timestamp), int(p.kf), sim3.mul(T_kf[p.kf], p.T_CkCf))
            )
    return rows


def write_depth_maps(
    out_dir: str | Path, system: SlamSystem, K: FloatArray, origin: str = ""
) -> int:
    """Write the depth files of every posed frame into ``out_dir``; returns how many frames.

    Args:
        out_dir: the ``depth/`` folder (created).
        system: the finished :class:`~mslam.system.SlamSystem`.
        K: (3, 3) intrinsics at the pointmap resolution.
        origin: where they came from (a comment line in ``intrinsics.txt``).
    """
    from mslam.export.observer import _keyframe_pointmap

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if len(system.keyframes) == 0:
        write_atomic(out_dir / "frames.txt", "")
        return 0
    H, W = system.keyframes[0].shape
    world: dict[int, tuple[FloatArray, FloatArray]] = {}
    lines = []
    for index, ts, k, T_WC in _frame_rows(system):
        if k not in world:
            X, C = _keyframe_pointmap(system, k)
            world[k] = (sim3.act(system.keyframes[k].T_WC, X.reshape(-1, 3)), C.reshape(-1))
        depth, conf = render_depth(*world[k], T_WC, K, (H, W))
        _save(out_dir, index, depth, conf)
        t, q = T_WC[:3], so3.normalize(T_WC[3:7])
        lines.append(" ".join([str(index), repr(ts), str(k), *(repr(float(x)) for x in (*t, *q))]))
    write_atomic(out_dir / "frames.txt", "\n".join(lines) + "\n")
    fx, fy, cx, cy = (float(K[r, c]) for r, c in ((0, 0), (1, 1), (0, 2), (1, 2)))
    head = f"# width height fx fy cx cy; {origin}\n" if origin else ""
    write_atomic(out_dir / "intrinsics.txt", f"{head}{W} {H} {fx!r} {fy!r} {cx!r} {cy!r}\n")
    return len(lines)


def _save(out_dir: Path, index: int, depth: np.ndarray, conf: np.ndarray) -> None:
    stem = f"{index:06d}"
    mm = np.where(conf > C_CONF_THRESHOLD, depth * PNG_DEPTH_SCALE, 0.0)
    ok, enc = cv2.imencode(".png", np.clip(np.rint(mm), 0, 65535).astype(np.uint16))
    if not ok:
        raise OSError(f"cannot encode {stem}.png")
    write_atomic(out_dir / f"{stem}.png", enc.tobytes())
    for name, arr in ((f"{stem}.npy", depth), (f"{stem}_conf.npy", conf)):
        with open(out_dir / name, "wb") as fh:
            np.save(fh, arr.astype(np.float32))
