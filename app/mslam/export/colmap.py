"""The final map as a COLMAP sparse model (``mslam run --colmap DIR``).

COLMAP's model files (text ``cameras.txt``, ``images.txt``, ``points3D.txt`` and the same in
binary, ``*.bin``) with:

* one ``PINHOLE`` camera at the pointmap resolution: the run's intrinsics (given in calibrated
  mode, else estimated from the pointmaps, ``mslam.export.camera``), shifted by half a pixel to
  COLMAP's convention (the top-left pixel's centre is (0.5, 0.5));
* one image per keyframe (or, with ``all_frames``, per posed frame), named ``NNNNNN.png`` after
  the frame index and written into ``DIR/images/``; its pose is the world-to-camera inverse of
  the rigid pose in ``keyframes.txt`` / ``trajectory.txt`` (Sim(3) scale dropped);
* one 3-D point per confident keyframe pixel on a grid (``C / N > 1.5``, the PLY's points;
  a pixel stride keeps at most :data:`MAX_POINTS_PER_IMAGE` per keyframe), coloured from the
  keyframe image, with a track of one observation (its keyframe image at its pixel) and the
  reprojection error through the exported camera.

Public names, in reading order:
    ColmapModel, colmap_model, write_colmap_text, write_colmap_binary, write_colmap
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mslam.atomic import write_atomic
from mslam.system.frontend import SlamSystem
from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray

__all__ = [
    "ColmapModel",
    "colmap_model",
    "write_colmap",
    "write_colmap_binary",
    "write_colmap_text",
]

#: At most this many 3-D points per keyframe (a pixel stride thins larger pointmaps).
MAX_POINTS_PER_IMAGE = 16384
#: Average-confidence threshold of the exported points (the PLY's).
C_CONF_THRESHOLD = 1.5
_PINHOLE_MODEL_ID = 1


@dataclass
class ColmapModel:
    """A COLMAP model in memory; I images (image ``n`` has id ``n + 1``), P points (point
    ``p`` has id ``p + 1``).

    Attributes:
        camera: (width, height, fx, fy, cx, cy) in COLMAP's pixel convention.
        names: (I,) image names.
        qvec: (I, 4) world-to-camera rotations, ``qw qx qy qz``.
        tvec: (I, 3) world-to-camera translations.
        frame_index: (I,) the frame index of each image.
        xy: per image, (M_n, 2) observed pixel positions.
        point_ids: per image, (M_n,) the ids of the observed points.
        xyz: (P, 3) points.
        rgb: (P, 3) uint8 colours.
        error: (P,) reprojection error in pixels.
        point_image: (P,) id of the image observing each point.
        point_idx: (P,) the point's index among that image's observations.
        camera_origin: where the intrinsics came from (a comment in ``cameras.txt``).
    """

    camera: tuple[int, int, float, float, float, float]
    names: list[str]
    qvec: FloatArray
    tvec: FloatArray
    frame_index: np.ndarray
    xy: list[FloatArray] = field(default_factory=list)
    point_ids: list[np.ndarray] = field(default_factory=list)
    xyz: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    error: FloatArray = field(default_factory=lambda: np.zeros(0))
    point_image: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    point_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    camera_origin: str = ""


def _world_to_camera(T_WC: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(qw qx qy qz) and t of the rigid inverse of Sim(3) ``T_WC`` (scale dropped)."""
    q = so3.normalize(np.asarray(T_WC[3:7], np.float64))
    R_cw = so3.to_matrix(q).T
    qi = so3.conj(q)
    return np.array([qi[3], qi[0], qi[1], qi[2]]), -R_cw @ np.asarray(T_WC[:3], np.float64)


def _posed_images(system: SlamSystem, all_frames: bool) -> list[tuple[int, int, FloatArray]]:
    """(frame index, keyframe or -1, T_WC) of each image, keyframes from their final pose."""
    kf_of = {int(kf.frame.index): k for k, kf in enumerate(system.keyframes)}
    T_kf = system.keyframes.poses()
    if not all_frames:
        return [(int(kf.frame.index), k, T_kf[k]) for k, kf in enumerate(system.keyframes)]
    rows: dict[int, tuple[int, int, FloatArray]] = {}
    for p in system.poses:
        if 0 <= p.kf < len(system.keyframes):
            k = kf_of.get(int(p.index), -1)
            T = T_kf[k] if k >= 0 else sim3.mul(T_kf[p.kf], p.T_CkCf)
            rows[int(p.index)] = (int(p.index), k, T)
    return [rows[i] for i in sorted(rows)]


def colmap_model(system: SlamSystem, K: FloatArray, all_frames: bool = False) -> ColmapModel:
    """Build the model of a finished run.

    Args:
        system: the :class:`~mslam.system.SlamSystem`.
        K: (3, 3) intrinsics at the pointmap resolution (pixel-centre convention).
        all_frames: one image per posed frame instead of per keyframe.
    """
    from mslam.export.observer import _keyframe_pointmap, keyframe_colours

    H, W = system.keyframes[0].shape if len(system.keyframes) else (0, 0)
    stride = max(1, int(np.ceil(np.sqrt(H * W / MAX_POINTS_PER_IMAGE))))
    rows = _posed_images(system, all_frames)
    qt = [_world_to_camera(T) for _, _, T in rows]
    model = ColmapModel(
        camera=(W, H, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5),
        names=[f"{i:06d}.png" for i, _, _ in rows],
        qvec=np.array([q for q, _ in qt]).reshape(-1, 4),
        tvec=np.array([t for _, t in qt]).reshape(-1, 3),
        frame_index=np.array([i for i, _, _ in rows], np.int64),
    )
    v, u = np.mgrid[stride // 2 : H : stride, stride // 2 : W : stride]
    xyz: list[FloatArray] = []
    rgb: list[np.ndarray] = []
    err: list[FloatArray] = []
    img_id: list[np.ndarray] = []
    idx: list[np.ndarray] = []
    for n, (_, k, _) in enumerate(rows):
        if k < 0:
            model.xy.append(np.zeros((0, 2)))
            model.point_ids.append(np.zeros(0, np.int64))
            continue
        X, C = _keyframe_pointmap(system, k)
        Xg, Cg = X[v, u], C[v, u]
        keep = (Cg > C_CONF_THRESHOLD) & np.all(np.isfinite(Xg), axis=-1) & (Xg[..., 2] > 0)
        Xw = sim3.act(system.keyframes[k].T_WC, Xg[keep])
        xy = np.stack([u[keep], v[keep]], axis=-1) + 0.5
        first = sum(len(a) for a in xyz)
        model.xy.append(xy.astype(np.float64))
        model.point_ids.append(np.arange(first, first + len(Xw), dtype=np.int64) + 1)
        xyz.append(Xw)
        rgb.append(keyframe_colours(system, k)[v, u][keep])
        err.append(_reprojection_error(Xw, model.qvec[n], model.tvec[n], model.camera, xy))
        img_id.append(np.full(len(Xw), n + 1, np.int64))
        idx.append(np.arange(len(Xw), dtype=np.int64))
    if xyz:
        model.xyz, model.rgb, model.error = (
            np.concatenate(xyz),
            np.concatenate(rgb),
            np.concatenate(err),
        )
        model.point_image, model.point_idx = np.concatenate(img_id), np.concatenate(idx)
    return model


def _reprojection_error(
    Xw: FloatArray, qvec: FloatArray, tvec: FloatArray, cam: tuple, xy: FloatArray
) -> FloatArray:
    R = so3.to_matrix(np.array([qvec[1], qvec[2], qvec[3], qvec[0]]))
    Xc = Xw @ R.T + tvec
    z = np.where(Xc[:, 2] > 1e-12, Xc[:, 2], np.inf)
    proj = np.stack([cam[2] * Xc[:, 0] / z + cam[4], cam[3] * Xc[:, 1] / z + cam[5]], axis=-1)
    e = np.linalg.norm(proj - xy, axis=-1)
    return np.where(np.isfinite(e), e, 0.0)


def write_colmap_text(out_dir: str | Path, model: ColmapModel) -> None:
    """``cameras.txt``, ``images.txt``, ``points3D.txt`` (COLMAP's text model)."""
    out_dir = Path(out_dir)
    W, H, fx, fy, cx, cy = model.camera
    origin = f"# Intrinsics: {model.camera_origin}\n" if model.camera_origin else ""
    write_atomic(out_dir / "cameras.txt", f"# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n{origin}"
                 f"# Number of cameras: 1\n1 PINHOLE {W} {H} {fx!r} {fy!r} {cx!r} {cy!r}\n")  # fmt: skip
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(model.names)}"]  # fmt: skip
    for n, name in enumerate(model.names):
        nums = " ".join(repr(float(x)) for x in (*model.qvec[n], *model.tvec[n]))
        lines.append(f"{n + 1} {nums} 1 {name}")
        obs = [
            f"{x!r} {y!r} {int(p)}" for (x, y), p in zip(model.xy[n].tolist(), model.point_ids[n])
        ]
        lines.append(" ".join(obs))
    write_atomic(out_dir / "images.txt", "\n".join(lines) + "\n")
    lines = ["# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(model.xyz)}"]  # fmt: skip
    for p, (X, c, e, im, ix) in enumerate(
        zip(
            model.xyz.tolist(),
            model.rgb.tolist(),
            model.error.tolist(),
            model.point_image,
            model.point_idx,
        )
    ):
        lines.append(
            f"{p + 1} {X[0]!r} {X[1]!r} {X[2]!r} {c[0]} {c[1]} {c[2]} {e!r} {int(im)} {int(ix)}"
        )
    write_atomic(out_dir / "points3D.txt", "\n".join(lines) + "\n")


def write_colmap_binary(out_dir: str | Path, model: ColmapModel) -> None:
    """``cameras.bin``, ``images.bin``, ``points3D.bin`` (COLMAP's binary model, little-endian)."""
    out_dir = Path(out_dir)
    W, H, fx, fy, cx, cy = model.camera
    cams = struct.pack("<QiiQQ4d", 1, 1, _PINHOLE_MODEL_ID, W, H, fx, fy, cx, cy)
    write_atomic(out_dir / "cameras.bin", cams)
    parts = [struct.pack("<Q", len(model.names))]
    for n, name in enumerate(model.names):
        parts.append(struct.pack("<i7di", n + 1, *model.qvec[n], *model.tvec[n], 1))
        parts.append(name.encode() + b"\0")
        parts.append(struct.pack("<Q", len(model.xy[n])))
        obs = np.zeros(len(model.xy[n]), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
        obs["x"], obs["y"], obs["id"] = model.xy[n][:, 0], model.xy[n][:, 1], model.point_ids[n]
        parts.append(obs.tobytes())
    write_atomic(out_dir / "images.bin", b"".join(parts))
    rec = np.zeros(len(model.xyz), dtype=[("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3),
                   ("err", "<f8"), ("n", "<u8"), ("im", "<i4"), ("ix", "<i4")])  # fmt: skip
    rec["id"] = np.arange(1, len(model.xyz) + 1)
    rec["xyz"], rec["rgb"], rec["err"], rec["n"] = model.xyz, model.rgb, model.error, 1
    rec["im"], rec["ix"] = model.point_image, model.point_idx
    write_atomic(out_dir / "points3D.bin", struct.pack("<Q", len(rec)) + rec.tobytes())


def write_colmap(
    out_dir: str | Path,
    system: SlamSystem,
    sequence: Any,
    K: FloatArray,
    all_frames: bool = False,
    origin: str = "",
) -> ColmapModel:
    """Write the text and binary model and the images into ``out_dir``; returns the model.

    Images of keyframes come from the keyframes; those of other frames are read again from
    ``sequence`` and resized to the pointmap resolution. ``origin`` (where ``K`` came from)
    becomes a comment in ``cameras.txt``.
    """
    from mslam.export.observer import keyframe_colours

    model = colmap_model(system, K, all_frames)
    model.camera_origin = origin
    out_dir = Path(out_dir)
    kf_of = {int(kf.frame.index): k for k, kf in enumerate(system.keyframes)}
    W, H = model.camera[:2]
    for name, i in zip(model.names, model.frame_index):
        k = kf_of.get(int(i))
        img = keyframe_colours(system, k) if k is not None else sequence[int(i)].rgb
        if img.shape[:2] != (H, W):
            img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        ok, enc = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
        if not ok:
            raise OSError(f"cannot encode {name}")
        write_atomic(out_dir / "images" / name, enc.tobytes())
    write_colmap_text(out_dir, model)
    write_colmap_binary(out_dir, model)
    return model
