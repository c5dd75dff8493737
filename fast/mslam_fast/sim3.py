"""Taichi twin of ``mslam_ref.sim3`` — same names, parameters and shapes; see there for the maths.

Each public function validates its inputs with the reference's checks, coerces them to the
runtime dtype, broadcasts and flattens the leading batch axes, runs one parallel loop over the
batch (one element per iteration, no reductions) and reshapes the output back. The building
blocks are the ``@ti.func`` in ``mslam_fast._kernels.sim3``, which matching, tracking and the
backend reuse inside their fused kernels.
"""

import math
from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._kernels import sim3 as K
from mslam_fast._runtime import ensure_init, flat, prepare, run_batch
from mslam_fast._types import nd
from mslam_ref.conventions import SIM3_SIGMA_MAX, as_float_array, sim3_tangent

# fmt: off
__all__ = [  # in reading order
    "exp", "log", "mul", "inv", "act", "act_and_jacobian", "adjoint",
    "adjoint_inv_apply", "retract", "to_matrix",
]
# fmt: on

Array = np.ndarray[Any, Any]


# --- batch kernels: one per public function, so every ti.func is testable on its own ---------


@ti.kernel
def _exp_k(xi: nd, out: nd):
    for i in range(xi.shape[0]):
        K.store(out, i, K.sim3_exp(K.load(xi, i, 7)))


@ti.kernel
def _log_k(T: nd, out: nd):
    for i in range(T.shape[0]):
        K.store(out, i, K.sim3_log(K.load(T, i, 8)))


@ti.kernel
def _mul_k(A: nd, B: nd, out: nd):
    for i in range(A.shape[0]):
        K.store(out, i, K.sim3_mul(K.load(A, i, 8), K.load(B, i, 8)))


@ti.kernel
def _inv_k(T: nd, out: nd):
    for i in range(T.shape[0]):
        K.store(out, i, K.sim3_inv(K.load(T, i, 8)))


@ti.kernel
def _act_k(T: nd, X: nd, out: nd):
    for i in range(T.shape[0]):
        K.store(out, i, K.sim3_act(K.load(T, i, 8), K.load(X, i, 3)))


@ti.kernel
def _act_jac_k(T: nd, X: nd, out: nd, J: nd):
    for i in range(T.shape[0]):
        P = K.sim3_act(K.load(T, i, 8), K.load(X, i, 3))
        K.store(out, i, P)
        K.store_mat(J, i, K.sim3_act_jacobian(P))


@ti.kernel
def _adjoint_k(T: nd, out: nd):
    for i in range(T.shape[0]):
        K.store_mat(out, i, K.sim3_adjoint(K.load(T, i, 8)))


@ti.kernel
def _adj_inv_k(T: nd, J: nd, out: nd):
    for i in range(T.shape[0]):
        K.store(out, i, K.sim3_adj_inv_apply(K.load(T, i, 8), K.load(J, i, 7)))


@ti.kernel
def _retract_k(T: nd, xi: nd, out: nd):
    for i in range(T.shape[0]):
        K.store(out, i, K.sim3_retract(K.load(T, i, 8), K.load(xi, i, 7)))


@ti.kernel
def _to_matrix_k(T: nd, out: nd):
    for i in range(T.shape[0]):
        T_i = K.load(T, i, 8)
        R = K.quat_to_matrix(K.quat(T_i))
        for r in ti.static(range(3)):
            for c in ti.static(range(3)):
                out[i, r, c] = T_i[7] * R[r, c]
            out[i, r, 3] = T_i[r]
            out[i, 3, r] = 0.0
        out[i, 3, 3] = 1.0


# --- host wrappers -------------------------------------------------------------------------


def _T(T: Any, name: str = "T") -> Array:
    """Validate like ``mslam_ref.sim3.validate`` (shape, finite, s > 0, non-zero quaternion, same
    messages), normalise the quaternion, coerce to the runtime dtype.

    Cheaper than calling the reference's ``validate``: one finiteness pass instead of two, and the
    copy that normalises is made only when some quaternion is not unit to 1e-12 already (skipping
    the division then changes the result by < 1e-12, far inside the parity tolerance).
    """
    arr = as_float_array(T, name, 8)
    if np.any(arr[..., 7] <= 0.0):
        raise ValueError(f"{name}: scale s (index 7) must be positive")
    q = arr[..., 3:7]
    n2 = np.einsum("...i,...i->...", q, q)
    if np.any(n2 < 1e-24):
        raise ValueError(f"{name}: quaternion has (near) zero norm and cannot be normalised")
    if np.any(np.abs(n2 - 1.0) > 1e-12):
        arr = arr.copy()
        arr[..., 3:7] /= np.sqrt(n2)[..., None]
    return np.ascontiguousarray(arr, dtype=ensure_init().dtype)


def _xi(xi: Any) -> Array:
    """Validate a tangent like ``mslam_ref.sim3.exp`` (same error; in float32 the |sigma| cap
    is 75, where e^sigma sigma^2 still fits), coerce to the runtime dtype."""
    dtype = ensure_init().dtype
    cap = SIM3_SIGMA_MAX if dtype == np.float64 else 75.0
    return np.ascontiguousarray(sim3_tangent(xi, "xi", cap), dtype=dtype)


def exp(xi: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.exp``."""
    return run_batch(_exp_k, [(_xi(xi), 7)], (8,))


def log(T: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.log`` (3x3 inverse of W per element)."""
    return run_batch(_log_k, [(_T(T), 8)], (7,))


def mul(A: Any, B: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.mul``."""
    return run_batch(_mul_k, [(_T(A, "A"), 8), (_T(B, "B"), 8)], (8,))


def inv(T: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.inv``."""
    return run_batch(_inv_k, [(_T(T), 8)], (8,))


def act(T: Any, X: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.act``."""
    return run_batch(_act_k, [(_T(T), 8), (prepare(X, "X", 3), 3)], (3,))


def act_and_jacobian(T: Any, X: Any) -> tuple[Array, Array]:
    """Taichi twin of ``mslam_ref.sim3.act_and_jacobian``; P and J come from one fused loop."""
    T_, X_ = _T(T), prepare(X, "X", 3)
    batch = np.broadcast_shapes(T_.shape[:-1], X_.shape[:-1])
    dtype = ensure_init().dtype
    P = np.empty((*batch, 3), dtype=dtype)
    J = np.empty((*batch, 3, 7), dtype=dtype)
    if math.prod(batch) > 0:
        _act_jac_k(flat(T_, batch, 8), flat(X_, batch, 3), P.reshape(-1, 3), J.reshape(-1, 3, 7))
    return P, J


def adjoint(T: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.adjoint``."""
    return run_batch(_adjoint_k, [(_T(T), 8)], (7, 7))


def adjoint_inv_apply(T: Any, J: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.adjoint_inv_apply``."""
    return run_batch(_adj_inv_k, [(_T(T), 8), (prepare(J, "J", 7), 7)], (7,))


def retract(T: Any, xi: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.retract``."""
    return run_batch(_retract_k, [(_T(T), 8), (_xi(xi), 7)], (8,))


def to_matrix(T: Any) -> Array:
    """Taichi twin of ``mslam_ref.sim3.to_matrix``."""
    return run_batch(_to_matrix_k, [(_T(T), 8)], (4, 4))
