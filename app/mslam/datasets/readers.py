"""docs/upstream.md §10 — reading images, depth maps, calibration files and pose files, with clear errors.

Every reader names the offending file (and line, for text files) in its error. Depth images
are 16-bit PNGs scaled by ``depth_scale`` (TUM: 5000 per metre, 7-Scenes: 1000); 0 and 65535
mean "no measurement" and become 0 m.

Public names, in reading order:
    Calibration, read_calibration, colour_registration_maps, calibration_yaml, read_rgb,
    read_depth, encode_png,
    read_pose_matrix, matrix_to_T_WC, read_text_rows, natsorted
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from mslam_ref import sim3
from mslam_ref.conventions import FloatArray

__all__ = [
    "Calibration",
    "calibration_yaml",
    "colour_registration_maps",
    "encode_png",
    "matrix_to_T_WC",
    "natsorted",
    "read_calibration",
    "read_depth",
    "read_pose_matrix",
    "read_rgb",
    "read_text_rows",
]

#: Raw 16-bit depth values that mean "invalid".
DEPTH_INVALID = (0, 65535)


@dataclass(frozen=True)
class Calibration:
    """Camera calibration in upstream's YAML form (``--calib`` file, docs/upstream.md §10.3).

    Attributes:
        width, height: image size the intrinsics refer to.
        fx, fy, cx, cy: pinhole intrinsics (pixel-centre convention).
        distortion: OpenCV coefficients ``(k1, k2, p1, p2[, k3])``, empty when none.
        depth_scale: raw depth units per metre, or None when not given.
        colour: ``(fx, fy, cx, cy[, k1, k2, p1, p2[, k3]])`` of the colour camera (OpenCV's
            distortion model) when its images are not registered
            to the depth images (7-Scenes: the Kinect's colour camera sees a wider field than
            its depth camera, whose intrinsics ``fx, fy, cx, cy`` then are). The colour images
            are resampled onto the depth camera's pixel grid (``colour_registration_maps``),
            so both share ``K``. None when they are registered (TUM) or there is no depth.
        colour_auto: estimate ``colour`` from the images' edges when the sequence is loaded
            (``mslam.datasets.registration``): True for ``colour_calibration: auto``, False
            for ``colour_calibration: none``, None when the file does not say (the loader
            decides: 7-Scenes folders estimate, others do not).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()
    depth_scale: float | None = None
    colour: tuple[float, ...] | None = None
    colour_auto: bool | None = None

    @property
    def K(self) -> FloatArray:
        """(3, 3) intrinsics matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return any(abs(d) > 0 for d in self.distortion)


def read_calibration(path: str | Path) -> Calibration:
    """Read upstream's calibration YAML: ``width``, ``height``, ``calibration: [fx, fy, cx, cy,
    (k1, k2, p1, p2[, k3])]`` and optionally ``depth_scale`` and (ours) ``colour_calibration:
    [fx, fy, cx, cy, (k1, k2, p1, p2[, k3])]`` (:attr:`Calibration.colour`).

    Upstream: main.py (``--calib``) and dataloader.py::Intrinsics.from_calib.

    Raises:
        FileNotFoundError: missing file.
        ValueError: unparsable YAML, a missing key, or bad values, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: calibration file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (YAML) file") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}:" if mark is not None else ""
        problem = " ".join(str(getattr(exc, "problem", None) or "").split())
        raise ValueError(f"{path}:{where} not a valid YAML file ({problem or 'syntax'})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping with width, height, calibration")
    missing = [k for k in ("width", "height", "calibration") if k not in data]
    if missing:
        raise ValueError(f"{path}: missing key(s) {', '.join(missing)}")
    cal = data["calibration"]
    if not isinstance(cal, list) or len(cal) not in (4, 8, 9):
        raise ValueError(
            f"{path}: 'calibration' must be [fx, fy, cx, cy] or [fx, fy, cx, cy, k1, k2, p1, p2"
            f"(, k3)], got {cal!r}"
        )
    try:
        vals = [float(v) for v in cal]
        width, height = int(data["width"]), int(data["height"])
        depth_scale = None if data.get("depth_scale") is None else float(data["depth_scale"])
    except (TypeError, ValueError):
        raise ValueError(f"{path}: non-numeric width, height, calibration or depth_scale") from None
    if width < 1 or height < 1 or vals[0] <= 0 or vals[1] <= 0 or not np.all(np.isfinite(vals)):
        raise ValueError(f"{path}: width, height, fx, fy must be positive and finite")
    if depth_scale is not None and depth_scale <= 0:
        raise ValueError(f"{path}: depth_scale must be positive, got {depth_scale}")
    fx, fy, cx, cy = vals[:4]
    colour_cal = data.get("colour_calibration")
    auto = {"auto": True, "none": False}.get(colour_cal) if isinstance(colour_cal, str) else None
    colour = None if auto is not None else _colour_intrinsics(path, colour_cal, len(vals) > 4)
    return Calibration(
        width, height, fx, fy, cx, cy, tuple(vals[4:]), depth_scale, colour,
        False if colour is not None else auto,
    )  # fmt: skip


def _colour_intrinsics(path: Path, cal: Any, distorted: bool) -> tuple[float, ...] | None:
    """``colour_calibration`` of a calibration YAML as ``(fx, fy, cx, cy, distortion...)``, or
    None."""
    if cal is None:
        return None
    if distorted:
        raise ValueError(f"{path}: colour_calibration cannot be combined with distortion")
    try:
        vals = [float(v) for v in cal]
    except (TypeError, ValueError):
        vals = []
    if len(vals) not in (4, 8, 9) or vals[0] <= 0 or vals[1] <= 0 or not np.all(np.isfinite(vals)):
        raise ValueError(
            f"{path}: colour_calibration must be [fx, fy, cx, cy(, k1, k2, p1, p2(, k3))] with "
            "fx, fy > 0, 'auto' or 'none'"
        )
    return tuple(vals)


def colour_registration_maps(calib: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (H, W) float32 that resample a colour image onto the depth camera's
    pixel grid: depth pixel (u, v) looks along ``x = ((u - cx) / fx, (v - cy) / fy)``, which
    the colour camera sees at ``(cx_c, cy_c) + (fx_c, fy_c) · d(x)``, with ``d`` its lens
    distortion (OpenCV's radial-tangential model; the identity without coefficients). The
    cameras' small offset (a few centimetres on a Kinect) is neglected. Needs
    ``calib.colour``."""
    if calib.colour is None:
        raise ValueError("colour_registration_maps: the calibration has no colour intrinsics")
    fx_c, fy_c, cx_c, cy_c, *dist = calib.colour
    u, v = np.meshgrid(np.arange(calib.width, dtype=np.float64), np.arange(calib.height))
    x, y = (u - calib.cx) / calib.fx, (v - calib.cy) / calib.fy
    k1, k2, p1, p2, k3 = (*dist, 0.0, 0.0, 0.0, 0.0, 0.0)[:5]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return (cx_c + fx_c * xd).astype(np.float32), (cy_c + fy_c * yd).astype(np.float32)


def calibration_yaml(
    K: FloatArray, width: int, height: int, depth_scale: float | None = None, dist=()
) -> str:
    """The text of a calibration YAML for :func:`read_calibration`."""
    cal = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), *map(float, dist)]
    lines = [f"width: {int(width)}", f"height: {int(height)}", f"calibration: {cal!r}"]
    if depth_scale is not None:
        lines.append(f"depth_scale: {float(depth_scale)!r}")
    return "\n".join(lines) + "\n"


def _read_bytes(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise ValueError(f"{path}: empty {what} file")
    if path.suffix.lower() in (".jpg", ".jpeg") and b"\xff\xd9" not in data[-64:].tobytes():
        raise ValueError(f"{path}: truncated JPEG (no end-of-image marker)")
    return data


def read_rgb(path: str | Path) -> np.ndarray:
    """Read a colour (or grey) image as (H, W, 3) uint8 RGB.

    Raises:
        FileNotFoundError: missing file. ValueError: unreadable, truncated or non-8-bit image.
    """
    path = Path(path)
    data = _read_bytes(path, "image")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: unreadable or truncated image")
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(
    path: str | Path, depth_scale: float, shape: tuple[int, int] | None = None
) -> FloatArray:
    """Read a 16-bit depth PNG as (H, W) float64 metres; invalid (0, 65535) becomes 0.

    Args:
        path: depth image; depth_scale: raw units per metre; shape: expected (H, W) or None.

    Raises:
        FileNotFoundError / ValueError naming the file (unreadable, not single-channel 16-bit,
        wrong size).
    """
    path = Path(path)
    raw = cv2.imdecode(_read_bytes(path, "depth image"), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"{path}: unreadable or truncated depth image")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ValueError(f"{path}: expected a single-channel 16-bit depth image, got {raw.dtype}")
    if shape is not None and raw.shape != tuple(shape):
        raise ValueError(f"{path}: depth size {raw.shape} does not match the image size {shape}")
    z = raw.astype(np.float64) / float(depth_scale)
    z[np.isin(raw, DEPTH_INVALID)] = 0.0
    return z


def encode_png(img: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 (H, W, 3) or a uint16 (H, W) image."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV failure
        raise ValueError("could not encode PNG")
    return buf.tobytes()


def read_text_rows(path: str | Path, min_cols: int) -> list[list[str]]:
    """Whitespace- (or comma-) separated rows of a text index, skipping ``#`` comments.

    Raises:
        FileNotFoundError; ValueError naming the file and line when a row is too short.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) < min_cols:
            raise ValueError(f"{path}:{n}: expected at least {min_cols} columns, got {line!r}")
        rows.append(parts)
    return rows


def read_pose_matrix(path: str | Path) -> FloatArray:
    """A 4x4 pose matrix from a text file (7-Scenes ``frame-XXXXXX.pose.txt``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pose file not found")
    try:
        M = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: not a numeric 4x4 matrix ({exc})") from None
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise ValueError(f"{path}: expected a finite 4x4 matrix, got shape {M.shape}")
    return M


def matrix_to_T_WC(M: FloatArray) -> FloatArray:
    """Sim(3) 8-vector (s = 1) of a 4x4 rigid matrix; the 3x3 block is first projected to the
    nearest rotation (SVD), since stored matrices are often slightly non-orthonormal."""
    U, _, Vt = np.linalg.svd(M[:3, :3])
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    P = np.eye(4)
    P[:3, :3], P[:3, 3] = R, M[:3, 3]
    return sim3.from_matrix(P)


def natsorted(paths) -> list[Path]:
    """Sort paths naturally (``img2`` before ``img10``)."""

    def key(p: Path):
        return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", Path(p).name)]

    return sorted((Path(p) for p in paths), key=key)
