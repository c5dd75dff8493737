"""Example conformance adapter: check a differently named Sim(3) API against the golden set.

    mslam conformance export golden
    mslam conformance check golden --impl examples/conformance/adapter_example.py

An adapter is a Python file that defines ``KERNELS``, a dict from kernel names (as listed in
the golden set's ``index.json``) to callables with the reference's signature: NumPy arrays in
the reference's layout in, the reference's results out. Here each callable converts
``T = [tx, ty, tz, qx, qy, qz, qw, s]`` to the library's ``[qw, qx, qy, qz, t, log s]`` and
back. Kernels the adapter leaves out are reported as absent and not checked.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import other_sim3  # found beside this file

NAME = "other_sim3 via examples/conformance/adapter_example.py"


def to_theirs(T: np.ndarray) -> np.ndarray:
    """mslam layout (..., 8) -> the library's (..., 8); the quaternion is normalised."""
    T = np.asarray(T, dtype=np.float64)
    q = T[..., 3:7] / np.linalg.norm(T[..., 3:7], axis=-1, keepdims=True)
    return np.concatenate([q[..., 3:4], q[..., :3], T[..., :3], np.log(T[..., 7:8])], -1)


def from_theirs(P: np.ndarray) -> np.ndarray:
    """The library's layout (..., 8) -> mslam's."""
    return np.concatenate([P[..., 4:7], P[..., 1:4], P[..., :1], np.exp(P[..., 7:8])], -1)


KERNELS = {
    "sim3.mul": lambda A, B: from_theirs(other_sim3.compose(to_theirs(A), to_theirs(B))),
    "sim3.inv": lambda T: from_theirs(other_sim3.inverse(to_theirs(T))),
    "sim3.act": lambda T, X: other_sim3.apply(to_theirs(T), np.asarray(X, dtype=np.float64)),
    "sim3.to_matrix": lambda T: other_sim3.as_matrix(to_theirs(T)),
}
