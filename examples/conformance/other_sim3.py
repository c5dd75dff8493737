"""A stand-in for "your own kernels": a tiny Sim(3) library with another API and layout.

Poses are ``[qw, qx, qy, qz, tx, ty, tz, log_s]`` (scalar-first quaternion, log-scale), the
functions have other names, and it is written directly from the maths (x -> s R x + t),
independently of ``mslam_ref``. ``adapter_example.py`` maps it onto the conformance kernels.
"""

from __future__ import annotations

import numpy as np


def rotation(q_wxyz: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrix of a unit quaternion (..., 4) in w, x, y, z order."""
    w, x, y, z = np.moveaxis(q_wxyz, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def hamilton(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p q of (..., 4) wxyz quaternions."""
    pw, pv, qw, qv = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    w = pw * qw - np.sum(pv * qv, -1, keepdims=True)
    v = pw * qv + qw * pv + np.cross(pv, qv)
    return np.concatenate([w, v], -1)


def apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """s R x + t for (..., 8) poses and (..., 3) points."""
    R = rotation(pose[..., :4])
    Rx = np.einsum("...ij,...j->...i", R, points)
    return np.exp(pose[..., 7:8]) * Rx + pose[..., 4:7]


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a b: (s_a s_b, R_a R_b, s_a R_a t_b + t_a)."""
    q = hamilton(a[..., :4], b[..., :4])
    t = apply(a, b[..., 4:7])
    return np.concatenate([q, t, a[..., 7:8] + b[..., 7:8]], -1)


def inverse(a: np.ndarray) -> np.ndarray:
    """a^-1: (1/s, R^T, -R^T t / s)."""
    q = a[..., :4] * np.array([1.0, -1.0, -1.0, -1.0])
    inv = np.concatenate([q, np.zeros_like(a[..., 4:7]), -a[..., 7:8]], -1)
    t = -apply(inv, a[..., 4:7])
    return np.concatenate([q, t, -a[..., 7:8]], -1)


def as_matrix(a: np.ndarray) -> np.ndarray:
    """(..., 4, 4) homogeneous matrix [[s R, t], [0, 1]]."""
    M = np.zeros((*a.shape[:-1], 4, 4))
    M[..., :3, :3] = np.exp(a[..., 7:8, None]) * rotation(a[..., :4])
    M[..., :3, 3] = a[..., 4:7]
    M[..., 3, 3] = 1.0
    return M
