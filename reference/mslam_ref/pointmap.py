"""Paper §3.1 and docs/upstream.md §10 — pixels, rays, pointmaps and the network-resolution image.

A *pointmap* is an (H, W, 3) image of 3-D points, one per pixel, in some camera frame. With
known intrinsics K, a metric depth image z gives one by back-projection along the camera
rays; without K, MASt3R predicts it directly. Pixel convention everywhere in the system
(docs/upstream.md §10.2): the integer pixel ``(u, v) = (column, row)`` is the pixel *centre*, so the ray
of pixel (u, v) is ``[(u - cx)/fx, (v - cy)/fy, 1]`` and back-projection is
``X = z · [(u - cx)/fx, (v - cy)/fy, 1]``.

The second half reproduces upstream's image preparation: the resize to long side 512 (or short
side 224 with a square crop) and the centre crop to multiples of 16 (``resize_img``), the
matching change of intrinsics, the optional undistortion with a re-centred principal point,
and the network's input normalisation to [-1, 1].

Public functions, in reading order:
    pixel_grid, camera_rays, backproject, project, normalize_rays, scale_intrinsics,
    resize_img, intrinsics_after_resize, optimal_intrinsics, undistort_maps, undistort,
    network_input
"""

from __future__ import annotations

import cv2
import numpy as np

from mslam_ref.conventions import FloatArray, as_float_array

__all__ = [
    "backproject",
    "camera_rays",
    "intrinsics_after_resize",
    "network_input",
    "normalize_rays",
    "optimal_intrinsics",
    "pixel_grid",
    "project",
    "resize_img",
    "scale_intrinsics",
    "undistort",
    "undistort_maps",
]


def _check_K(K: FloatArray) -> FloatArray:
    K = as_float_array(K, "K", (3, 3))
    if K.ndim != 2 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("K: expected a (3, 3) intrinsics matrix with fx, fy > 0")
    return K


def _check_size(H: int, W: int) -> None:
    if int(H) < 1 or int(W) < 1:
        raise ValueError(f"image size: H and W must be positive, got H={H}, W={W}")


def pixel_grid(H: int, W: int) -> FloatArray:
    """Pixel-centre coordinates ``(u, v)`` of an H x W image.

    Upstream: mast3r_slam/geometry.py::get_pixel_coords (u = column, v = row).

    Returns:
        (H, W, 2) float64, ``grid[v, u] = (u, v)``.
    """
    _check_size(H, W)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([u, v], axis=-1)


def camera_rays(K: FloatArray, H: int, W: int) -> FloatArray:
    """Unnormalised camera rays with unit z: ``r(u, v) = [(u - cx)/fx, (v - cy)/fy, 1]``.

    Paper: §3.1 (calibrated case, rays from K). Upstream: geometry.py::backproject-style
    ``K^-1 [u, v, 1]`` (no skew).

    Args:
        K: (3, 3) intrinsics.
        H, W: image size.

    Returns:
        (H, W, 3) float64 rays; ``z · r`` is the point at z-depth ``z``.
    """
    K = _check_K(K)
    g = pixel_grid(H, W)
    x = (g[..., 0] - K[0, 2]) / K[0, 0]
    y = (g[..., 1] - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def backproject(depth: FloatArray, K: FloatArray) -> FloatArray:
    """Pointmap of a z-depth image: ``X(u, v) = z(u, v) · [(u - cx)/fx, (v - cy)/fy, 1]``.

    Paper: §3.1. Upstream: dataloader / geometry back-projection with the pixel-centre
    convention (docs/upstream.md §10.2).

    Args:
        depth: (H, W) z-depth in metres (any finite values; 0 gives the camera centre).
        K: (3, 3) intrinsics.

    Returns:
        (H, W, 3) float64 points in the camera frame.
    """
    depth = as_float_array(depth, "depth")
    if depth.ndim != 2:
        raise ValueError(f"depth: expected (H, W), got shape {depth.shape}")
    return depth[..., None] * camera_rays(K, *depth.shape)


def project(X: FloatArray, K: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Pinhole projection ``(u, v) = (fx x/z + cx, fy y/z + cy)``.

    Args:
        X: (..., 3) points in the camera frame.
        K: (3, 3) intrinsics.

    Returns:
        uv: (..., 2) pixel coordinates (NaN-free: z is clamped away from 0 with its sign kept).
        z: (...,) depth of each point (unclamped).
    """
    X = as_float_array(X, "X", 3)
    K = _check_K(K)
    z = X[..., 2]
    zc = np.where(np.abs(z) < 1e-12, np.copysign(1e-12, z), z)
    u = K[0, 0] * X[..., 0] / zc + K[0, 2]
    v = K[1, 1] * X[..., 1] / zc + K[1, 2]
    return np.stack([u, v], axis=-1), z


def normalize_rays(X: FloatArray) -> FloatArray:
    """Unit rays ``ψ(x) = x / ‖x‖`` (paper §3.2); zero vectors map to (0, 0, 1).

    Args:
        X: (..., 3) points.

    Returns:
        (..., 3) unit vectors.
    """
    X = as_float_array(X, "X", 3)
    n = np.linalg.norm(X, axis=-1, keepdims=True)
    out = X / np.where(n > 0, n, 1.0)
    out[(n[..., 0] == 0)] = (0.0, 0.0, 1.0)
    return out


def scale_intrinsics(
    K: FloatArray, src_size: tuple[int, int], dst_size: tuple[int, int], half_pixel: bool = True
) -> FloatArray:
    """Intrinsics of an image resized from ``src_size = (W1, H1)`` to ``dst_size = (W2, H2)``.

    With ``half_pixel=True`` (exact for pixel-centre sampling as in ``cv2.resize``):
    ``cx' = (cx + 0.5) W2/W1 - 0.5``; with ``half_pixel=False`` upstream's plain multiplication
    ``cx' = cx W2/W1`` (docs/upstream.md §10.2). Focal lengths scale by ``W2/W1`` and ``H2/H1``.

    Returns:
        (3, 3) float64 intrinsics.
    """
    K = _check_K(K).copy()
    (W1, H1), (W2, H2) = src_size, dst_size
    _check_size(H1, W1)
    _check_size(H2, W2)
    sx, sy = W2 / W1, H2 / H1
    off = 0.5 if half_pixel else 0.0
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + off) * sx - off
    K[1, 2] = (K[1, 2] + off) * sy - off
    return K


def _resized_size(W1: int, H1: int, long_edge: int) -> tuple[int, int]:
    S = max(W1, H1)
    return round(W1 * long_edge / S), round(H1 * long_edge / S)


def resize_img(
    img: np.ndarray, size: int = 512, square_ok: bool = False
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Upstream's resize and centre crop of an RGB image to the network resolution.

    Upstream: mast3r_slam/mast3r_utils.py::resize_img (docs/upstream.md §10.1). For ``size = 512`` the long
    side becomes 512 (``new = round(x · 512 / max(W1, H1))``), then a centre crop with
    ``cx = W//2, cy = H//2, halfw = ((2 cx)//16)·8, halfh = ((2 cy)//16)·8`` (``halfh = 3 halfw/4``
    for a square image unless ``square_ok``) makes both sides multiples of 16. For ``size = 224``
    the short side becomes 224 and a square centre crop follows. Upstream uses PIL LANCZOS
    (shrinking) / BICUBIC (enlarging); this uses cv2 INTER_LANCZOS4 / INTER_CUBIC, which differ
    by a few grey levels.

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
    interp = cv2.INTER_LANCZOS4 if max(W1, H1) > long_edge else cv2.INTER_CUBIC
    res = cv2.resize(img, (W, H), interpolation=interp)
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


def intrinsics_after_resize(
    K: FloatArray, transform: tuple[float, float, float, float]
) -> FloatArray:
    """Intrinsics of the resized and cropped image (upstream's ``K_frame``, docs/upstream.md §10.2).

    Upstream: dataloader.py::Intrinsics.from_calib. ``fx' = fx / scale_w``,
    ``cx' = cx / scale_w - half_crop_w`` (plain multiplication, no half-pixel correction).

    Args:
        K: (3, 3) intrinsics of the (undistorted) full-resolution image.
        transform: from :func:`resize_img`.

    Returns:
        (3, 3) float64 intrinsics.
    """
    K = _check_K(K).copy()
    scale_w, scale_h, half_crop_w, half_crop_h = transform
    K[0, 0] /= scale_w
    K[1, 1] /= scale_h
    K[0, 2] = K[0, 2] / scale_w - half_crop_w
    K[1, 2] = K[1, 2] / scale_h - half_crop_h
    return K


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
    K = _check_K(K)
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
    K = _check_K(K)
    dist = as_float_array(dist, "dist").reshape(-1)
    mx, my = cv2.initUndistortRectifyMap(
        K, dist, None, _check_K(K_opt), (int(W), int(H)), cv2.CV_32FC1
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


def network_input(img: np.ndarray) -> np.ndarray:
    """Network input tensor data: ``(img / 255 - 0.5) / 0.5`` in [-1, 1], NCHW.

    Upstream: dust3r ImgNorm = ToTensor + Normalize((0.5,)*3, (0.5,)*3).

    Args:
        img: (H, W, 3) uint8.

    Returns:
        (1, 3, H, W) float32.
    """
    img = np.asarray(img)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"img: expected uint8 (H, W, 3), got {img.dtype} {img.shape}")
    x = img.astype(np.float32) / 255.0
    return ((x - 0.5) / 0.5).transpose(2, 0, 1)[None].copy()
