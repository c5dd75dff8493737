"""docs/upstream.md §10.3 — the TUM RGB-D layout: reading it, and writing any sequence into it.

Layout: ``rgb.txt`` and ``depth.txt`` (``timestamp filename``), ``associations.txt``
(``t_rgb rgb_file t_depth depth_file``, from TUM's associate.py), ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``, camera-to-world), 16-bit depth PNGs at 5000 units per
metre, and (ours, optional) ``calib.yaml`` in upstream's calibration format.

Public names, in reading order:
    TUM_CALIB, load_tum, write_tum_sequence
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from mslam.datasets.files import FileSequence, apply_calibration
from mslam.datasets.frame import FrameSequence
from mslam.datasets.readers import (
    Calibration,
    calibration_yaml,
    encode_png,
    read_text_rows,
)
from mslam.formats import read_tum
from mslam_ref.conventions import FloatArray

__all__ = ["TUM_CALIB", "load_tum", "write_tum_sequence"]

#: Upstream's built-in TUM calibrations (config/intrinsics; docs/upstream.md §10.3), 640x480.
TUM_CALIB = {
    "freiburg1": [517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633],
    "freiburg2": [520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172],
    "freiburg3": [535.4, 539.2, 320.1, 247.6],
}

#: Largest timestamp difference (s) accepted when associating streams (TUM associate.py).
MAX_DT = 0.02


def _ground_truth(path: Path) -> tuple[FloatArray, FloatArray]:
    """``groundtruth.txt`` as timestamps (M,) and Sim(3) poses (M, 8), s = 1, unit quaternions."""
    stamps, tq = read_tum(path)
    q = tq[:, 3:7] / np.linalg.norm(tq[:, 3:7], axis=1, keepdims=True)
    return stamps, np.concatenate([tq[:, :3], q, np.ones((len(tq), 1))], axis=1)


def _nearest(t: FloatArray, ref: FloatArray, max_dt: float) -> np.ndarray:
    """Index into ``ref`` of the nearest stamp for each ``t`` (-1 beyond ``max_dt``)."""
    if len(ref) == 0:
        return np.full(len(t), -1)
    order = np.argsort(ref)
    rs = ref[order]
    k = np.clip(np.searchsorted(rs, t), 1, max(len(rs) - 1, 1))
    k0 = np.clip(k - 1, 0, len(rs) - 1)
    pick = np.where(np.abs(rs[k0] - t) <= np.abs(rs[np.minimum(k, len(rs) - 1)] - t), k0, k)
    pick = np.minimum(pick, len(rs) - 1)
    idx = order[pick]
    return np.where(np.abs(ref[idx] - t) <= max_dt, idx, -1)


def load_tum(
    folder: str | Path,
    calib: Calibration | str | Path | None = None,
    size: tuple[int, int] | None = None,
) -> FileSequence:
    """Load a TUM-layout folder.

    Frames come from ``associations.txt`` when present (RGB with depth), otherwise from
    ``rgb.txt`` (depth associated from ``depth.txt`` by nearest stamp within 20 ms, if present).
    Ground truth is the nearest ``groundtruth.txt`` pose within 20 ms. Calibration: ``calib``,
    else ``calib.yaml`` in the folder, else upstream's built-in freiburg1/2/3 intrinsics when the
    folder name says so, else none (uncalibrated). Depth: 5000 units per metre unless the
    calibration gives ``depth_scale``; outside the TUM and ETH3D datasets themselves that is an
    assumption, recorded as ``depth_scale_assumed`` (the run's summary says so).

    Raises:
        FileNotFoundError: a missing index file, naming it.
        ValueError: a malformed index file, naming it.
    """
    folder = Path(folder)
    assoc, rgb_txt = folder / "associations.txt", folder / "rgb.txt"
    depth_paths = None
    if assoc.is_file():
        rows = read_text_rows(assoc, 4)
        stamps = [float(r[0]) for r in rows]
        rgb_paths = [folder / r[1] for r in rows]
        depth_paths = [folder / r[3] for r in rows]
    elif rgb_txt.is_file():
        rows = read_text_rows(rgb_txt, 2)
        stamps = [float(r[0]) for r in rows]
        rgb_paths = [folder / r[1] for r in rows]
        if (folder / "depth.txt").is_file():
            drows = read_text_rows(folder / "depth.txt", 2)
            idx = _nearest(np.array(stamps), np.array([float(r[0]) for r in drows]), MAX_DT)
            keep = idx >= 0
            if keep.any():
                stamps = [s for s, k in zip(stamps, keep) if k]
                rgb_paths = [p for p, k in zip(rgb_paths, keep) if k]
                depth_paths = [folder / drows[i][1] for i in idx[keep]]
    else:
        raise FileNotFoundError(f"{rgb_txt}: TUM index not found (nor associations.txt)")
    if not rgb_paths:
        raise ValueError(f"{assoc if assoc.is_file() else rgb_txt}: lists no frames")
    T_WC = None
    gt = folder / "groundtruth.txt"
    if gt.is_file():
        gt_t, gt_T = _ground_truth(gt)
        idx = _nearest(np.array(stamps), gt_t, MAX_DT)
        T_WC = [gt_T[k] if k >= 0 else None for k in idx]
    eth3d = folder / "calibration.txt"
    named = [vals for key, vals in TUM_CALIB.items() if key in folder.name]
    freiburg = named[-1] if named else None  # the camera the folder's name gives
    cal = apply_calibration(calib)
    if cal is None and (folder / "calib.yaml").is_file():
        cal = apply_calibration(folder / "calib.yaml")
    if cal is None and eth3d.is_file():
        cal = _eth3d_calibration(eth3d, rgb_paths[0])
    if cal is None and freiburg is not None:
        fx, fy, cx, cy = freiburg[:4]
        cal = Calibration(640, 480, fx, fy, cx, cy, tuple(freiburg[4:]), 5000.0)
    # 5000 per metre is stated by the TUM and ETH3D datasets; any other folder in their layout
    # (a camera that stores millimetres) may differ unless its calibration says so.
    stated = freiburg is not None or eth3d.is_file()
    return FileSequence(folder.name, rgb_paths, stamps, depth_paths, T_WC, cal, 5000.0, size,
                        depth_scale_assumed=not stated)  # fmt: skip


def _eth3d_calibration(path: Path, first_rgb: Path) -> Calibration | None:
    """ETH3D SLAM's ``calibration.txt`` (one line ``fx fy cx cy``); None for other contents."""
    from mslam.datasets.readers import read_rgb

    rows = [r for r in path.read_text().splitlines() if r.strip() and not r.startswith("#")]
    try:
        vals = [float(x) for x in rows[0].split()] if len(rows) == 1 else []
    except ValueError:
        return None
    if len(vals) != 4:
        return None
    H, W = read_rgb(first_rgb).shape[:2]
    fx, fy, cx, cy = vals
    return Calibration(W, H, fx, fy, cx, cy, (), 5000.0)


def _tum_line(t: float, T: FloatArray) -> str:
    return f"{t:.6f} " + " ".join(f"{v:.9f}" for v in T[:7])


def write_tum_sequence(
    seq: FrameSequence, out: str | Path, depth_scale: float = 5000.0, overwrite=False
):
    """Write a sequence in TUM layout (plus ``calib.yaml``) into ``out``, all or nothing.

    Everything is written into a temporary sibling folder first and renamed at the end, so an
    error leaves no partial output. Depth is stored as ``round(z · depth_scale)`` (0 = invalid,
    values beyond 65534 become 0).

    Args:
        seq: any :class:`FrameSequence` (frames with depth get ``depth/``; poses, if any,
            ``groundtruth.txt``; ``K``, if any, ``calib.yaml``).
        out: destination folder; must not exist or be empty unless ``overwrite``.

    Returns:
        the output folder as a Path.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"{out}: folder exists and is not empty (use overwrite)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        (tmp / "rgb").mkdir()
        rgb_lines, depth_lines, assoc, gt = [], [], [], []
        H = W = None
        for frame in seq:
            t = frame.timestamp
            name = f"{t:.6f}.png"
            (tmp / "rgb" / name).write_bytes(encode_png(frame.rgb))
            rgb_lines.append(f"{t:.6f} rgb/{name}")
            H, W = frame.shape
            if frame.depth is not None:
                (tmp / "depth").mkdir(exist_ok=True)
                raw = np.round(frame.depth * depth_scale)
                raw = np.where((raw > 0) & (raw < 65535), raw, 0).astype(np.uint16)
                (tmp / "depth" / name).write_bytes(encode_png(raw))
                depth_lines.append(f"{t:.6f} depth/{name}")
                assoc.append(f"{t:.6f} rgb/{name} {t:.6f} depth/{name}")
            if frame.T_WC is not None:
                gt.append(_tum_line(t, frame.T_WC))
        head = f"# {seq.name}: written by mslam\n# timestamp filename\n"
        (tmp / "rgb.txt").write_text(head + "\n".join(rgb_lines) + "\n")
        if depth_lines:
            (tmp / "depth.txt").write_text(head + "\n".join(depth_lines) + "\n")
            (tmp / "associations.txt").write_text("\n".join(assoc) + "\n")
        if gt:
            (tmp / "groundtruth.txt").write_text(
                "# timestamp tx ty tz qx qy qz qw (camera-to-world)\n" + "\n".join(gt) + "\n"
            )
        if seq.K is not None and W is not None and H is not None:
            ds = depth_scale if depth_lines else None
            (tmp / "calib.yaml").write_text(calibration_yaml(seq.K, W, H, ds))
        if out.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            out.rename(old / "x")
            tmp.rename(out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
