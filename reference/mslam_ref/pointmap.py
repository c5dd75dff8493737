"""Paper §3.1 and docs/upstream.md §10 — pixels, rays, pointmaps and the network-resolution image.

A *pointmap* is an (H, W, 3) image of 3-D points, one per pixel, in some camera frame. With
known intrinsics K, a metric depth image z gives one by back-projection along the camera
rays; without K, MASt3R predicts it directly. Pixel convention everywhere in the system
(docs/upstream.md §10.2): the integer pixel ``(u, v) = (column, row)`` is the pixel *centre*, so the ray
of pixel (u, v) is ``[(u - cx)/fx, (v - cy)/fy, 1]`` and back-projection is
``X = z · [(u - cx)/fx, (v - cy)/fy, 1]``.

The second half is the maths of upstream's image preparation: the intrinsics after a resize
and centre crop (the image operations themselves, which need OpenCV, live in the
application's ``mslam.datasets.images``) and the network's input normalisation to [-1, 1].

Public functions, in reading order:
    check_K, intrinsics_from_fov, pixel_grid, strided_pixels, camera_rays, backproject, project, normalize_rays,
    scale_intrinsics, intrinsics_after_resize, network_input
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_ref.conventions import FloatArray, as_float_array

__all__ = [
    "backproject",
    "camera_rays",
    "check_K",
    "intrinsics_from_fov",
    "intrinsics_after_resize",
    "network_input",
    "normalize_rays",
    "pixel_grid",
    "strided_pixels",
    "project",
    "scale_intrinsics",
]


def check_K(K: Any) -> FloatArray:
    """Validate a (3, 3) pinhole intrinsics matrix (fx, fy > 0); returns it as float64."""
    K = as_float_array(K, "K", (3, 3))
    if K.ndim != 2 or K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise ValueError("K: expected a (3, 3) intrinsics matrix with fx, fy > 0")
    return K


def _check_size(H: int, W: int) -> None:
    if int(H) < 1 or int(W) < 1:
        raise ValueError(f"image size: H and W must be positive, got H={H}, W={W}")


def intrinsics_from_fov(width: int, height: int, fov_deg: float) -> FloatArray:
    """Pinhole intrinsics with horizontal field of view ``fov_deg`` and square pixels.

    ``fx = fy = (W / 2) / tan(fov / 2)``, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2`` (the centre
    of the image under the pixel-centre convention, as upstream's re-centred ``K_opt``).

    Returns:
        (3, 3) float64.
    """
    if int(width) < 2 or int(height) < 2:
        raise ValueError(f"width, height: must be >= 2, got {width}x{height}")
    if not 1.0 < fov_deg < 170.0:
        raise ValueError(f"fov_deg: must be in (1, 170), got {fov_deg}")
    f = (width / 2.0) / np.tan(np.deg2rad(fov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def pixel_grid(H: int, W: int) -> FloatArray:
    """Pixel-centre coordinates ``(u, v)`` of an H x W image.

    Upstream: mast3r_slam/geometry.py::get_pixel_coords (u = column, v = row).

    Returns:
        (H, W, 2) float64, ``grid[v, u] = (u, v)``.
    """
    _check_size(H, W)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([u, v], axis=-1)


def strided_pixels(H: int, W: int, stride: int) -> np.ndarray:
    """(H, W) bool mask of a regular pixel grid: every ``stride``-th row and column, starting
    at ``stride // 2`` (all pixels when ``stride`` is 1).

    The subsets of pixels that carry residuals or matches when not every pixel is needed
    (about ``H·W / stride²`` of them, spread evenly over the image).
    """
    if stride < 1:
        raise ValueError(f"stride: expected >= 1, got {stride}")
    grid = np.zeros((H, W), dtype=bool)
    grid[stride // 2 :: stride, stride // 2 :: stride] = True
    return grid


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
    K = check_K(K)
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
    K = check_K(K)
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
    K = check_K(K).copy()
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
    K = check_K(K).copy()
    scale_w, scale_h, half_crop_w, half_crop_h = transform
    K[0, 0] /= scale_w
    K[1, 1] /= scale_h
    K[0, 2] = K[0, 2] / scale_w - half_crop_w
    K[1, 2] = K[1, 2] / scale_h - half_crop_h
    return K


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
