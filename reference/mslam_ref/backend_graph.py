"""Paper §3.5 — Backend data: the pose graph's fixed arrays, validated once.

What stays constant while the backend moves the keyframe poses: the canonical pointmaps and
their confidences, the directed blocks (i <- j) with their matches and qualities, and in
calibrated mode the intrinsics (the pointmaps are then constrained to their rays, as
upstream's ``solve_GN_calib`` does). ``mslam_ref.backend`` re-exports every public name.

Public names, in reading order:
    PoseGraph, pose_graph, check_poses
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mslam_ref import calib, sim3
from mslam_ref.conventions import BoolArray, FloatArray, IntArray, as_float_array
from mslam_ref.pointmap import check_K

__all__ = ["PoseGraph", "check_poses", "pose_graph"]


@dataclasses.dataclass(frozen=True)
class PoseGraph:
    """The fixed data of the backend problem: what stays constant while the poses move.

    Build it with :func:`pose_graph`, which validates and converts the arrays.

    Attributes:
        X: (K, H, W, 3) canonical pointmaps, constrained to their rays when ``K_cam`` is given.
        C: (K, H, W) average confidences ``C / N``.
        ii, jj: (D,) int64 keyframe indices of each directed block (i <- j).
        idx: (D, N) int64 pixel of i matched to each pixel of j; valid: (D, N) bool;
            Q: (D, N) match quality.
        K_cam: None for the ray + distance residual, (3, 3) intrinsics for pixel + log-depth.
        pixels: None (every pixel of j has a residual, N = H·W) or (N,) int64: the pixels of
            j whose residuals the columns of idx, valid and Q hold (a subset keeps a solve's
            cost independent of the resolution; upstream uses every pixel).
    """

    X: FloatArray
    C: FloatArray
    ii: IntArray
    jj: IntArray
    idx: IntArray
    valid: BoolArray
    Q: FloatArray
    K_cam: FloatArray | None = None
    pixels: IntArray | None = None

    @property
    def n_blocks(self) -> int:
        """D, the number of directed blocks."""
        return len(self.ii)


def _keyframe_indices(ii: Any, jj: Any, n_kf: int) -> tuple[IntArray, IntArray]:
    ii, jj = (np.asarray(a).reshape(-1) for a in (ii, jj))
    for name, a in (("ii", ii), ("jj", jj)):
        if not np.issubdtype(a.dtype, np.integer) or (len(a) and (a.min() < 0 or a.max() >= n_kf)):
            raise ValueError(f"{name}: expected integer keyframe indices in [0, {n_kf})")
    if len(jj) != len(ii):
        raise ValueError(f"jj: expected {len(ii)} entries like ii, got {len(jj)}")
    return ii.astype(np.int64), jj.astype(np.int64)


def _pixel_indices(a: Any, name: str, shape: tuple[int, ...], n_pix: int) -> IntArray:
    a = np.asarray(a)
    if a.shape != shape or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name}: expected integer shape {shape}, got {a.dtype} {a.shape}")
    if a.size and (a.min() < 0 or a.max() >= n_pix):
        raise ValueError(f"{name}: pixel indices must lie in [0, {n_pix})")
    return a.astype(np.int64)


def pose_graph(
    X: Any,
    C: Any,
    ii: Any,
    jj: Any,
    idx: Any,
    valid: Any,
    Q: Any,
    K_cam: Any = None,
    pixels: Any = None,
) -> PoseGraph:
    """Validate and convert the backend's fixed data (shapes, index ranges, finiteness).

    The arguments are the attributes of :class:`PoseGraph`. X is constrained to its rays
    (``calib.constrain_points_to_ray``) when ``K_cam`` is given, as upstream's
    ``solve_GN_calib`` does.

    Raises:
        ValueError: naming the first argument that is wrong.
    """
    X = as_float_array(X, "X", 3)
    if X.ndim != 4:
        raise ValueError(f"X: expected (K, H, W, 3), got {X.shape}")
    C = as_float_array(C, "C")
    if C.shape != X.shape[:-1]:
        raise ValueError(f"C: expected shape {X.shape[:-1]}, got {C.shape}")
    n_pix = X.shape[1] * X.shape[2]
    ii, jj = _keyframe_indices(ii, jj, len(X))
    D = len(ii)
    if pixels is not None:
        pixels = _pixel_indices(pixels, "pixels", (np.asarray(pixels).size,), n_pix)
    N = n_pix if pixels is None else len(pixels)
    idx = _pixel_indices(idx, "idx", (D, N), n_pix)
    valid, Q = np.asarray(valid), as_float_array(Q, "Q")
    for name, a in (("valid", valid), ("Q", Q)):
        if a.shape != (D, N):
            raise ValueError(f"{name}: expected shape {(D, N)}, got {a.shape}")
    if K_cam is not None:
        K_cam = check_K(K_cam)
        X = calib.constrain_points_to_ray(X, K_cam)
    return PoseGraph(X, C, ii, jj, idx, valid.astype(bool), Q, K_cam, pixels)


def check_poses(T_WC: Any, graph: PoseGraph) -> FloatArray:
    """Validate ``T_WC`` (K, 8) against the graph's K keyframes; returns it as float64."""
    T_WC = sim3.validate(T_WC, "T_WC")
    if T_WC.ndim != 2 or len(T_WC) != len(graph.X):
        raise ValueError(f"T_WC: expected ({len(graph.X)}, 8), got {T_WC.shape}")
    return T_WC
