"""Taichi twin of ``mslam_ref.so3`` — same names, parameters and shapes; see there for the maths.

Each public function validates its inputs with the reference's checks, coerces them to the
runtime dtype, broadcasts and flattens the leading batch axes, runs one parallel loop over the
batch (one element per iteration, no reductions) and reshapes the output back. The building
blocks are the quaternion ``@ti.func`` in ``mslam_fast._kernels.sim3`` (``so3_exp``, ``so3_log``,
``quat_mul``, ``quat_conj``, ``quat_act``, ``quat_to_matrix``, ``quat_normalize``, ``hat``); each
is reached from the host through one small batch kernel below so that it has its own parity test.
``from_matrix`` runs on the host (Shepperd's branch choice per element is not worth a kernel).
"""

from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._kernels import sim3 as K
from mslam_fast._runtime import prepare, run_batch
from mslam_fast._types import nd

__all__ = [
    "act",
    "conj",
    "exp",
    "hat",
    "log",
    "mul",
    "normalize",
    "to_matrix",
]

Array = np.ndarray[Any, Any]


# --- batch kernels: one per public function ------------------------------------------------


@ti.kernel
def _exp_k(phi: nd, out: nd):
    for i in range(phi.shape[0]):
        K.store(out, i, K.so3_exp(K.load(phi, i, 3)))


@ti.kernel
def _log_k(q: nd, out: nd):
    for i in range(q.shape[0]):
        K.store(out, i, K.so3_log(K.quat_normalize(K.load(q, i, 4))))


@ti.kernel
def _normalize_k(q: nd, out: nd):
    for i in range(q.shape[0]):
        K.store(out, i, K.quat_normalize(K.load(q, i, 4)))


@ti.kernel
def _mul_k(q1: nd, q2: nd, out: nd):
    for i in range(q1.shape[0]):
        K.store(out, i, K.quat_mul(K.load(q1, i, 4), K.load(q2, i, 4)))


@ti.kernel
def _conj_k(q: nd, out: nd):
    for i in range(q.shape[0]):
        K.store(out, i, K.quat_conj(K.load(q, i, 4)))


@ti.kernel
def _act_k(q: nd, X: nd, out: nd):
    for i in range(q.shape[0]):
        K.store(out, i, K.quat_act(K.load(q, i, 4), K.load(X, i, 3)))


@ti.kernel
def _to_matrix_k(q: nd, out: nd):
    for i in range(q.shape[0]):
        K.store_mat(out, i, K.quat_to_matrix(K.load(q, i, 4)))


@ti.kernel
def _hat_k(v: nd, out: nd):
    for i in range(v.shape[0]):
        K.store_mat(out, i, K.hat(K.load(v, i, 3)))


# --- host wrappers -------------------------------------------------------------------------


def _nonzero_quat(q: Any, name: str) -> Array:
    """Check like ``mslam_ref.so3.normalize`` (shape, finite, norm >= 1e-12); do not divide."""
    arr = prepare(q, name, 4)
    if np.any(np.einsum("...i,...i->...", arr, arr, dtype=np.float64) < 1e-24):
        raise ValueError(f"{name}: quaternion has (near) zero norm and cannot be normalised")
    return arr


def normalize(q: Any, name: str = "q") -> Array:
    """Taichi twin of ``mslam_ref.so3.normalize`` (the norm check runs on the host)."""
    return run_batch(_normalize_k, [(_nonzero_quat(q, name), 4)], (4,))


def hat(v: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.hat``."""
    return run_batch(_hat_k, [(prepare(v, "v", 3), 3)], (3, 3))


def exp(phi: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.exp``."""
    return run_batch(_exp_k, [(prepare(phi, "phi", 3), 3)], (4,))


def log(q: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.log``; the quaternion is normalised inside the kernel."""
    return run_batch(_log_k, [(_nonzero_quat(q, "q"), 4)], (3,))


def mul(q1: Any, q2: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.mul``."""
    return run_batch(_mul_k, [(prepare(q1, "q1", 4), 4), (prepare(q2, "q2", 4), 4)], (4,))


def conj(q: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.conj``."""
    return run_batch(_conj_k, [(prepare(q, "q", 4), 4)], (4,))


def act(q: Any, X: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.act``."""
    return run_batch(_act_k, [(prepare(q, "q", 4), 4), (prepare(X, "X", 3), 3)], (3,))


def to_matrix(q: Any) -> Array:
    """Taichi twin of ``mslam_ref.so3.to_matrix``."""
    return run_batch(_to_matrix_k, [(prepare(q, "q", 4), 4)], (3, 3))
