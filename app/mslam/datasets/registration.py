"""Colour images not registered to the depth images: find the colour camera from edges.

Some RGB-D datasets store the colour and the depth of a two-camera sensor as they came, each on
its own pixel grid (7-Scenes: a Kinect v1, whose colour camera sees a wider field than its
depth camera; the dataset gives only the depth camera's intrinsics). A pointmap lifted from
the depth at a colour pixel then belongs to a slightly different ray, and every rotation
measured from colour matches comes out short by the ratio of the focal lengths (measured on
7-Scenes redkitchen: a rotation gain of 0.82 against 0.93 for a depth-only tracker;
benchmarks/RESULTS.md).

Depth discontinuities are colour edges too. For candidate colour intrinsics
``(s fx, s fy, cx, cy)`` the colour image is resampled onto the depth grid
(:func:`mslam.datasets.readers.colour_registration_maps`) and scored by the normalised
correlation of the two edge magnitudes, ``|∇ log z|`` and ``|∇ grey|``, over the valid depth
pixels of a few frames. A coarse-to-fine search over ``s`` keeps the best; it is used only when
it beats the identity (registered images) by :data:`MIN_GAIN`, so registered data (TUM,
synthetic) stays as it is. The cameras' few centimetres of baseline shift the colour edges by a
depth-dependent parallax (about 8 px at 2 m on 7-Scenes); a principal-point shift would absorb
part of it and raised the score, but it is not a property of the colour camera, and with it the
calibrated RGB-only run got worse (2.18 -> 2.51 cm; measured 2026-11-27), so only ``s`` is
searched.

Public names: estimate_colour_intrinsics, edge_score
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache
from typing import Any

import cv2
import numpy as np

from mslam.datasets.readers import Calibration, colour_registration_maps
from mslam_ref.conventions import FloatArray

__all__ = ["edge_score", "estimate_colour_intrinsics"]

#: Frames the score averages over (evenly spaced through the sequence).
FRAMES = 6
#: Colour focal / depth focal searched, in steps of ``ZOOM_STEP``, then ``ZOOM_FINE``.
ZOOM_RANGE, ZOOM_STEP, ZOOM_FINE = (0.80, 1.10), 0.02, 0.005
#: Least correlation gain over the identity for the estimate to be used.
MIN_GAIN = 0.03
#: The search runs at 1 / ``REDUCE`` of the image size.
REDUCE = 2


def _edges(img: np.ndarray) -> np.ndarray:
    """(H, W) float32 gradient magnitude."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1)
    return np.hypot(gx, gy)


def edge_score(depth_edges: np.ndarray, valid: np.ndarray, grey: np.ndarray, maps: Any) -> float:
    """Normalised correlation of depth edges and the remapped grey image's edges.

    Args:
        depth_edges: (H, W) ``|∇ log z|``; valid: (H, W) bool, pixels away from missing depth.
        grey: (H', W') float32 colour image in grey; maps: ``cv2.remap`` maps onto (H, W).
    """
    mx, my = maps
    g = cv2.remap(grey, mx, my, cv2.INTER_LINEAR)
    Hc, Wc = grey.shape
    m = valid & (mx > 1) & (mx < Wc - 2) & (my > 1) & (my < Hc - 2)
    if m.sum() < 100:
        return -1.0
    a, b = depth_edges[m], _edges(g)[m]
    a = (a - a.mean()) / (a.std() + 1e-9)
    b = (b - b.mean()) / (b.std() + 1e-9)
    return float(np.mean(a * b))


def _small(calib: Calibration, colour: tuple[float, ...]) -> Calibration:
    """``calib`` (with ``colour``) at 1 / REDUCE of its size."""
    r = 1.0 / REDUCE
    c = [v * r for v in colour[:4]]
    return replace(
        calib, width=calib.width // REDUCE, height=calib.height // REDUCE,
        fx=calib.fx * r, fy=calib.fy * r, cx=calib.cx * r, cy=calib.cy * r,
        distortion=(), colour=tuple(c),
    )  # fmt: skip


def estimate_colour_intrinsics(
    calib: Calibration, rgbs: list[np.ndarray], depths: list[FloatArray]
) -> tuple[tuple[float, float, float, float] | None, dict[str, float]]:
    """The colour camera's ``(fx, fy, cx, cy)`` on the depth camera's image plane, or None.

    Args:
        calib: the depth camera's calibration (full image size).
        rgbs: (H, W, 3) uint8 colour images; depths: (H, W) metres (0 = none), same frames.

    Returns:
        (the intrinsics, or None when the identity is as good: registered images), and a dict
        ``zoom`` (s), ``score`` (its correlation), ``identity_score``.
    """
    W, H = calib.width // REDUCE, calib.height // REDUCE
    data = []
    for rgb, depth in zip(rgbs, depths, strict=True):
        grey = cv2.cvtColor(cv2.resize(rgb, (W, H), interpolation=cv2.INTER_AREA),
                            cv2.COLOR_RGB2GRAY).astype(np.float32)  # fmt: skip
        z = cv2.resize(depth.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST)
        ok = z > 0
        log_z = np.where(ok, np.log(np.maximum(z, 1e-3)), 0).astype(np.float32)
        valid = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        if valid.mean() > 0.2:
            data.append((_edges(log_z), valid, grey))

    @cache  # the fine search revisits the coarse best, and the best is read once more
    def score(s: float) -> float:
        maps = colour_registration_maps(
            _small(calib, (s * calib.fx, s * calib.fy, calib.cx, calib.cy))
        )
        return float(np.mean([edge_score(e, v, g, maps) for e, v, g in data]))

    info = {"zoom": 1.0, "score": 0.0, "identity_score": 0.0}
    if not data:
        return None, info
    identity = score(1.0)
    coarse = np.arange(ZOOM_RANGE[0], ZOOM_RANGE[1] + 1e-9, ZOOM_STEP)
    s0 = float(max(coarse, key=lambda z: score(float(z))))
    fine = s0 + ZOOM_FINE * np.arange(-3, 4)
    best = float(max(fine, key=lambda z: score(float(z))))
    info.update(zoom=best, score=score(best), identity_score=identity)
    at_edge = not (ZOOM_RANGE[0] < best < ZOOM_RANGE[1])
    if info["score"] < identity + MIN_GAIN or at_edge:
        return None, info
    return (best * calib.fx, best * calib.fy, calib.cx, calib.cy), info
