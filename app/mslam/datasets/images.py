"""Image preparation — network-resolution resize/crop (Pillow) and undistortion (OpenCV).

The maths of these steps (intrinsics after a resize and crop, the pixel convention) is in
``mslam_ref.pointmap``; this module does the image operations themselves, as upstream's
data loader does (``mast3r_slam/mast3r_utils.py::resize_img``,
``mast3r_slam/dataloader.py::Intrinsics.from_calib``). The resize uses Pillow's filters as
upstream does, so the network input is bit for bit upstream's.

The one-parameter division model of an uncalibrated lens (:func:`division_undistort_points`,
:func:`division_maps`): a distorted pixel ``d`` with ``x_d = (d - c) / s`` (``c`` the image
centre, ``s`` its half diagonal in pixels) is undistorted to ``c + s · x_d / (1 + λ |x_d|²)``;
``λ < 0`` undoes barrel distortion, ``λ > 0`` pincushion. It needs no focal length, so an
uncalibrated run can estimate ``λ`` first (``mslam.priors.twoview_lens``).

Public functions, in reading order:
    resize_img, optimal_intrinsics, undistort_maps, undistort, centre_scale,
    division_undistort_points, division_maps
"""

from __future__ import annotations

import cv2
import numpy as np

from mslam_ref.conventions import FloatArray, as_float_array
from mslam_ref.pointmap import check_K

__all__ = [
    "centre_scale",
    "division_maps",
    "division_undistort_points",
    "optimal_intrinsics",
    "resize_img",
    "undistort",
    "undistort_maps",
]


def _resized_size(W1: int, H1: int, long_edge: int) -> tuple[int, int]:
    S = max(W1, H1)
    return round(W1 * long_edge / S), round(H1 * long_edge / S)


def _pil_resize(img: np.ndarray, W: int, H: int, shrink: bool) -> np.ndarray:
    """(H, W, 3) uint8: Pillow LANCZOS (``shrink``) or BICUBIC resize of an RGB image."""
    from PIL import Image

    resample = Image.Resampling.LANCZOS if shrink else Image.Resampling.BICUBIC
    return np.asarray(Image.fromarray(np.ascontiguousarray(img)).resize((W, H), resample))


def resize_img(
    img: np.ndarray, size: int = 512, square_ok: bool = False
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Upstream's resize and centre crop of an RGB image to the network resolution.

    Upstream: mast3r_slam/mast3r_utils.py::resize_img (docs/upstream.md §10.1). For ``size = 512`` the long
    side becomes 512 (``new = round(x · 512 / max(W1, H1))``), then a centre crop with
    ``cx = W//2, cy = H//2, halfw = ((2 cx)//16)·8, halfh = ((2 cy)//16)·8`` (``halfh = 3 halfw/4``
    for a square image unless ``square_ok``) makes both sides multiples of 16. For ``size = 224``
    the short side becomes 224 and a square centre crop follows. The resize is Pillow's
    ``Image.resize`` of the uint8 RGB image with LANCZOS when the long side shrinks and
    BICUBIC otherwise, as upstream's, so the output is bit for bit upstream's (OpenCV's
    INTER_LANCZOS4 / INTER_CUBIC differ from Pillow's filters by a few grey levels).

    Args:
        img: (H1, W1, 3) uint8 image.
        size: 512 or 224.
        square_ok: keep a square 512 image square.

    Returns:
        out: (H, W, 3) uint8 cropped image.
        transform: ``(scale_w, scale_h, half_crop_w, half_crop_h)`` with ``scale = W1 / W_res``
            (original over resized, before the crop) and the half-crops in resized pixels, as
            upstream's ``return_transformation``.
    """
    if size not in (224, 512):
        raise ValueError(f"size: must be 224 or 512, got {size}")
    img = np.asarray(img)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"img: expected uint8 (H, W, 3), got {img.dtype} {img.shape}")
    H1, W1 = img.shape[:2]
    if size == 224:
        long_edge = round(size * max(W1 / H1, H1 / W1))
    else:
        long_edge = size
    W, H = _resized_size(W1, H1, long_edge)
    res = _pil_resize(img, W, H, shrink=max(W1, H1) > long_edge)
    cx, cy = W // 2, H // 2
    if size == 224:
        half = min(cx, cy)
        halfw, halfh = half, half
    else:
        halfw, halfh = ((2 * cx) // 16) * 8, ((2 * cy) // 16) * 8
        if not square_ok and W == H:
            halfh = int(3 * halfw / 4)
    out = np.ascontiguousarray(res[cy - halfh : cy + halfh, cx - halfw : cx + halfw])
    transform = (W1 / W, H1 / H, (W - out.shape[1]) / 2, (H - out.shape[0]) / 2)
    return out, transform


def optimal_intrinsics(
    K: FloatArray, dist: FloatArray, W: int, H: int, center: bool = True
) -> FloatArray:
    """New camera matrix for undistortion with alpha = 0 and a (optionally) centred principal point.

    Upstream: dataloader.py::Intrinsics.from_calib, ``cv2.getOptimalNewCameraMatrix(K, dist,
    (W, H), 0, (W, H), centerPrincipalPoint=center)``. With ``center`` OpenCV puts the principal
    point at ((W-1)/2, (H-1)/2) and scales fx, fy by one factor so that every output pixel is
    valid.

    Args:
        K: (3, 3) intrinsics; dist: (4,) or (5,) OpenCV coefficients ``k1, k2, p1, p2[, k3]``.

    Returns:
        (3, 3) float64 ``K_opt``.
    """
    K = check_K(K)
    dist = as_float_array(dist, "dist").reshape(-1)
    K_opt, _ = cv2.getOptimalNewCameraMatrix(
        K, dist, (int(W), int(H)), 0, (int(W), int(H)), centerPrincipalPoint=bool(center)
    )
    return np.asarray(K_opt, dtype=np.float64)


def undistort_maps(
    K: FloatArray, dist: FloatArray, K_opt: FloatArray, W: int, H: int
) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables of ``cv2.initUndistortRectifyMap(K, dist, None, K_opt, (W, H), CV_32FC1)``.

    Returns:
        map_x, map_y: (H, W) float32 source coordinates of every output pixel.
    """
    K = check_K(K)
    dist = as_float_array(dist, "dist").reshape(-1)
    mx, my = cv2.initUndistortRectifyMap(
        K, dist, None, check_K(K_opt), (int(W), int(H)), cv2.CV_32FC1
    )
    return mx, my


def undistort(img: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Bilinear remap of an image (upstream: ``cv2.remap(img, mx, my, INTER_LINEAR)``).

    Args:
        img: (H, W, ...) image; maps: from :func:`undistort_maps` with the same H, W.

    Returns:
        (H, W, ...) undistorted image of the same dtype.
    """
    mx, my = maps
    if img.shape[:2] != mx.shape:
        raise ValueError(f"img: shape {img.shape[:2]} does not match the maps {mx.shape}")
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR)


def centre_scale(W: int, H: int) -> tuple[FloatArray, float]:
    """The image's centre ``c`` (2,) and half diagonal ``s`` in pixels: the units of the lens
    models here (``x = (uv − c) / s``) for a ``W`` x ``H`` image."""
    return np.array([(W - 1) / 2.0, (H - 1) / 2.0]), float(np.hypot(W, H) / 2.0)


def division_undistort_points(uv: FloatArray, lam: float, W: int, H: int) -> FloatArray:
    """(N, 2) pixels of a (W, H) image undistorted by the division model ``lam`` (module
    docstring); ``lam = 0`` returns them unchanged."""
    c, s = centre_scale(W, H)
    x = (np.asarray(uv, np.float64) - c) / s
    return c + s * x / (1.0 + lam * (x * x).sum(-1, keepdims=True))


def division_maps(lam: float, W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables that undistort a (W, H) image by the division model ``lam``: the distorted
    pixel of every output pixel (the model inverted by fixed-point iteration), for
    :func:`undistort` (borders replicated where ``lam > 0`` pulls the image inwards).

    Returns:
        map_x, map_y: (H, W) float32.
    """
    c, s = centre_scale(W, H)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    xu, yu = (u - c[0]) / s, (v - c[1]) / s
    xd, yd = xu.copy(), yu.copy()
    for _ in range(30):  # x_d = x_u (1 + lam |x_d|^2): a contraction for |lam| < 0.5
        r2 = xd * xd + yd * yd
        xd, yd = xu * (1.0 + lam * r2), yu * (1.0 + lam * r2)
    return (xd * s + c[0]).astype(np.float32), (yd * s + c[1]).astype(np.float32)
