"""Bundle adjustment — SE(3) rigid transforms in g2o's conventions (``VertexSE3Expmap``).

Layout:

* a group element is ``T = [tx, ty, tz, qx, qy, qz, qw]`` of shape ``(..., 7)``: translation and a
  unit Hamilton quaternion in xyzw order (the layout of ``mslam_ref.sim3`` without the scale). It
  maps world points into the camera, ``X_c = R(q) X_w + t`` (g2o ``SE3Quat``, world to camera);
* a tangent vector is ``xi = [omega, upsilon]`` of shape ``(..., 6)``: **rotation first**, then
  translation (g2o's order, the opposite of ``mslam_ref.sim3``);
* increments multiply on the **left**: ``retract(T, xi) = exp(xi) · T`` (g2o ``oplusImpl``).

The exponential uses the closed-form Rodrigues coefficients

    R = I + a1 [w]x + a2 [w]x^2,   V = I + a2 [w]x + a3 [w]x^2,   theta = |w|
    a1 = sin(theta)/theta, a2 = (1 - cos(theta))/theta^2, a3 = (theta - sin(theta))/theta^3

switching to their Taylor values (1, 1/2, 1/6) for ``theta < 1e-5`` as g2o and
cuda-bundle-adjustment do. Composition re-normalises the quaternion and picks ``w >= 0``.

Public functions, in reading order:
    identity, exp, log, mul, inv, act, act_and_jacobian, retract, to_matrix, from_matrix, validate

Upstream: g2o types/slam3d se3quat.h (SE3Quat::exp/log/operator*), g2o types/sba
``VertexSE3Expmap::oplusImpl``; cuda-bundle-adjustment src/cuda_block_solver.cu (the pose
exp-update kernel, quaternion from the trace).
"""

from __future__ import annotations

import numpy as np

from mslam_ref import so3
from mslam_ref.conventions import FloatArray, as_float_array

# fmt: off
__all__ = [  # in reading order
    "EPS_SE3", "identity", "exp", "log", "mul", "inv", "act",
    "act_and_jacobian", "retract", "to_matrix", "from_matrix", "validate",
]
# fmt: on

#: Small-angle switch of the Rodrigues coefficients (g2o / cuda-bundle-adjustment use 1e-5).
EPS_SE3 = 1e-5


def validate(T: FloatArray, name: str = "T") -> FloatArray:
    """Check an SE(3) array (trailing 7, finite) and return it with a unit quaternion, w >= 0.

    Args:
        T: (..., 7) ``[t, q_xyzw]``.
        name: argument name used in error messages.

    Returns:
        (..., 7) float64 copy with the quaternion normalised.
    """
    T = as_float_array(T, name, 7)
    q = so3.normalize(T[..., 3:], name)
    q = np.where(q[..., 3:] < 0.0, -q, q)
    return np.concatenate([T[..., :3], q], axis=-1)


def identity(batch: tuple[int, ...] = ()) -> FloatArray:
    """Identity elements ``[0, 0, 0, 0, 0, 0, 1]`` of shape ``(*batch, 7)``."""
    out = np.zeros((*batch, 7))
    out[..., 6] = 1.0
    return out


def _coefficients(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rodrigues coefficients a1, a2, a3 with the Taylor switch at ``theta < EPS_SE3``."""
    small = theta < EPS_SE3
    th = np.where(small, 1.0, theta)
    a1 = np.where(small, 1.0, np.sin(th) / th)
    a2 = np.where(small, 0.5, (1.0 - np.cos(th)) / th**2)
    a3 = np.where(small, 1.0 / 6.0, (th - np.sin(th)) / th**3)
    return a1, a2, a3


def exp(xi: FloatArray) -> FloatArray:
    """Tangent vector to group element.

    Upstream: g2o se3quat.h::SE3Quat::exp; cuda_block_solver.cu (pose update kernel).

        R = I + a1 W + a2 W^2,  V = I + a2 W + a3 W^2,  W = [omega]x,  t = V upsilon

    Args:
        xi: (..., 6) ``[omega, upsilon]``.

    Returns:
        (..., 7) ``[t, q_xyzw]`` with ``w >= 0``.
    """
    xi = as_float_array(xi, "xi", 6)
    w, ups = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(w, axis=-1)
    a1, a2, a3 = _coefficients(theta)
    W = so3.hat(w)
    W2 = W @ W
    eye = np.eye(3)
    R = eye + a1[..., None, None] * W + a2[..., None, None] * W2
    V = eye + a2[..., None, None] * W + a3[..., None, None] * W2
    t = np.einsum("...ij,...j->...i", V, ups)
    return np.concatenate([t, so3.from_matrix(R)], axis=-1)


def log(T: FloatArray) -> FloatArray:
    """Group element to tangent vector, ``|omega| <= pi``.

    Upstream: g2o se3quat.h::SE3Quat::log.

        omega = so3.log(q),  upsilon = V^-1 t,
        V^-1 = I - W/2 + (1/theta^2) (1 - a1 / (2 a2)) W^2     (series 1/12 below EPS_SE3)

    Args:
        T: (..., 7).

    Returns:
        (..., 6) ``[omega, upsilon]``.
    """
    T = validate(T)
    w = so3.log(T[..., 3:])
    theta = np.linalg.norm(w, axis=-1)
    small = theta < EPS_SE3
    th = np.where(small, 1.0, theta)
    c = np.where(small, 1.0 / 12.0, (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))) / th**2)
    W = so3.hat(w)
    Vinv = np.eye(3) - 0.5 * W + c[..., None, None] * (W @ W)
    ups = np.einsum("...ij,...j->...i", Vinv, T[..., :3])
    return np.concatenate([w, ups], axis=-1)


def mul(A: FloatArray, B: FloatArray) -> FloatArray:
    """Composition ``A · B`` (apply B first): ``t = t_A + R_A t_B``, ``q = q_A ⊗ q_B``.

    Args:
        A: (..., 7).
        B: (..., 7).

    Returns:
        (..., 7) with a re-normalised quaternion, ``w >= 0``.
    """
    A, B = validate(A, "A"), validate(B, "B")
    t = A[..., :3] + so3.act(A[..., 3:], B[..., :3])
    q = so3.mul(A[..., 3:], B[..., 3:])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., 3:] < 0.0, -q, q)
    return np.concatenate([t, q], axis=-1)


def inv(T: FloatArray) -> FloatArray:
    """Inverse ``[-R^T t, q*]``.

    Args:
        T: (..., 7).

    Returns:
        (..., 7).
    """
    T = validate(T)
    qc = so3.conj(T[..., 3:])
    t = -so3.act(qc, T[..., :3])
    q = np.where(qc[..., 3:] < 0.0, -qc, qc)
    return np.concatenate([t, q], axis=-1)


def act(T: FloatArray, X: FloatArray) -> FloatArray:
    """Transform points, ``Y = R X + t``.

    Args:
        T: (..., 7).
        X: (..., 3).

    Returns:
        (..., 3).
    """
    T = validate(T)
    X = as_float_array(X, "X", 3)
    return so3.act(T[..., 3:], X) + T[..., :3]


def act_and_jacobian(T: FloatArray, X: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``Y = T X`` with its Jacobians for the left increment and for the point.

    Upstream: g2o types_six_dof_expmap.cpp::EdgeSE3ProjectXYZ::linearizeOplus (the chain rule
    ``dY/dxi = [-[Y]x, I]`` it applies before the projection).

        d(exp(xi) T X)/d xi |_{xi=0} = [ -[Y]x , I ]   (3 x 6, omega columns first)
        d(T X)/d X = R

    Args:
        T: (..., 7).
        X: (..., 3).

    Returns:
        Y (..., 3), J_xi (..., 3, 6), J_X (..., 3, 3).
    """
    T = validate(T)
    X = as_float_array(X, "X", 3)
    Y = so3.act(T[..., 3:], X) + T[..., :3]
    J_xi = np.concatenate([-so3.hat(Y), np.broadcast_to(np.eye(3), (*Y.shape[:-1], 3, 3))], -1)
    R = np.broadcast_to(so3.to_matrix(T[..., 3:]), (*Y.shape[:-1], 3, 3))
    return Y, J_xi, R.copy()


def retract(T: FloatArray, xi: FloatArray) -> FloatArray:
    """Left update ``exp(xi) · T`` (g2o ``VertexSE3Expmap::oplusImpl``).

    Args:
        T: (..., 7).
        xi: (..., 6) ``[omega, upsilon]``.

    Returns:
        (..., 7).
    """
    return mul(exp(xi), T)


def to_matrix(T: FloatArray) -> FloatArray:
    """Homogeneous 4x4 matrix ``[[R, t], [0, 1]]``.

    Args:
        T: (..., 7).

    Returns:
        (..., 4, 4).
    """
    T = validate(T)
    out = np.zeros((*T.shape[:-1], 4, 4))
    out[..., :3, :3] = so3.to_matrix(T[..., 3:])
    out[..., :3, 3] = T[..., :3]
    out[..., 3, 3] = 1.0
    return out


def from_matrix(M: FloatArray) -> FloatArray:
    """Group element of a homogeneous 4x4 (or 3x4) rigid matrix.

    Args:
        M: (..., 4, 4) or (..., 3, 4).

    Returns:
        (..., 7) with ``w >= 0``.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.ndim < 2 or M.shape[-1] != 4 or M.shape[-2] not in (3, 4):
        raise ValueError(f"M: expected trailing shape (4, 4) or (3, 4), got {M.shape}")
    M = as_float_array(M, "M")
    return np.concatenate([M[..., :3, 3], so3.from_matrix(M[..., :3, :3])], axis=-1)
