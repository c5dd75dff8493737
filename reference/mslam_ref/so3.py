"""Paper §3.1 — SO(3) as unit quaternions, the rotation part of Sim(3).

Layout (lietorch / Eigen ``coeffs()`` order): a rotation is a unit Hamilton quaternion
``q = [qx, qy, qz, qw]`` of shape ``(..., 4)``; a tangent vector is ``phi (..., 3)``
(axis times angle). Every function broadcasts over leading batch axes and works in float64.
A wrong trailing shape or a NaN/inf entry raises ``ValueError`` naming the argument. Only ``log``
normalises its input; ``mul``, ``conj``, ``act`` and ``to_matrix`` take the quaternion as given
(unit by contract).

Public functions, in reading order:
    exp(phi)            -> q        rotation vector to quaternion
    log(q)              -> phi      quaternion to rotation vector, ||phi|| <= pi
    mul(q1, q2)         -> q1 ⊗ q2  Hamilton product
    conj(q)             -> q*       inverse of a unit quaternion
    act(q, X)           -> R(q) X   rotate points
    to_matrix(q)        -> R        (..., 3, 3)
    from_matrix(R)      -> q        (..., 4), w >= 0
    hat(v)              -> [v]x     (..., 3, 3) skew-symmetric matrix
    normalize(q)        -> q/||q||  with a clear error on zero or non-finite input

Upstream: lietorch include/so3.h and rxso3.h (quaternion Exp/Log, act), mast3r_slam
backend/src/gn_kernels.cu::actSO3 (the two-cross-product rotation).
"""

from __future__ import annotations

import numpy as np

from mslam_ref.conventions import EPS_EXP, FloatArray, as_float_array

__all__ = [
    "act",
    "conj",
    "exp",
    "from_matrix",
    "hat",
    "log",
    "mul",
    "normalize",
    "to_matrix",
]


def normalize(q: FloatArray, name: str = "q") -> FloatArray:
    """Return ``q / ||q||``; raise ``ValueError`` naming ``name`` on a zero or non-finite input.

    Args:
        q: (..., 4) quaternion ``[qx, qy, qz, qw]``, not necessarily unit.
        name: argument name used in error messages.

    Returns:
        (..., 4) unit quaternion.
    """
    q = as_float_array(q, name, 4)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError(f"{name}: quaternion has (near) zero norm and cannot be normalised")
    return q / n


def hat(v: FloatArray) -> FloatArray:
    """Skew-symmetric matrix ``[v]x`` with ``[v]x w = v x w``.

    Args:
        v: (..., 3) vector.

    Returns:
        (..., 3, 3) matrix.
    """
    v = as_float_array(v, "v", 3)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    V = np.zeros((*v.shape[:-1], 3, 3))
    V[..., 0, 1], V[..., 0, 2] = -z, y
    V[..., 1, 0], V[..., 1, 2] = z, -x
    V[..., 2, 0], V[..., 2, 1] = -y, x
    return V


def exp(phi: FloatArray) -> FloatArray:
    """Rotation vector to unit quaternion.

    Paper: §3.1 (Lie-group preliminaries). Upstream: lietorch so3.h::Exp.

        theta = ||phi||,  q = [sin(theta/2)/theta * phi, cos(theta/2)]

    Numerics: for theta < 1e-6 (lietorch's threshold) the coefficients use their Taylor
    series imag = 1/2 - theta^2/48 + theta^4/3840, real = 1 - theta^2/8 + theta^4/384.

    Args:
        phi: (..., 3) rotation vector.

    Returns:
        (..., 4) unit quaternion [qx, qy, qz, qw].
    """
    phi = as_float_array(phi, "phi", 3)
    th2 = np.sum(phi * phi, axis=-1)
    th = np.sqrt(th2)
    small = th < EPS_EXP
    th_safe = np.where(small, 1.0, th)
    imag = np.where(small, 0.5 - th2 / 48.0 + th2 * th2 / 3840.0, np.sin(0.5 * th_safe) / th_safe)
    real = np.where(small, 1.0 - th2 / 8.0 + th2 * th2 / 384.0, np.cos(0.5 * th_safe))
    return np.concatenate([imag[..., None] * phi, real[..., None]], axis=-1)


def log(q: FloatArray) -> FloatArray:
    """Unit quaternion to rotation vector with ``||phi|| <= pi``.

    Paper: §3.1. Upstream: lietorch so3.h::Log.

        n = ||q_v||,  phi = f * q_v,  f = 2 atan(n / w) / n

    Numerics: when n^2 < EPS^2 the series f = 2/w - (2/3) n^2 / w^3 is used; otherwise
    f = sign(w) 2 atan2(n, |w|) / n (sign(0) = +1), which is exact up to and including w = 0.
    lietorch uses f = +-pi / n when |w| < EPS, an angle error of up to 2 |w| (2e-6); this
    reference does not copy that. A negative w yields the shorter rotation (||phi|| <= pi).

    Args:
        q: (..., 4) quaternion; normalised first.

    Returns:
        (..., 3) rotation vector.
    """
    q = normalize(q)
    qv, w = q[..., :3], q[..., 3]
    n2 = np.sum(qv * qv, axis=-1)
    n = np.sqrt(n2)
    n_safe = np.where(n > 0.0, n, 1.0)
    w_safe = np.where(np.abs(w) > 0.0, w, 1.0)
    f_series = 2.0 / w_safe - (2.0 / 3.0) * n2 / w_safe**3
    f_gen = np.where(w >= 0.0, 2.0, -2.0) * np.arctan2(n, np.abs(w)) / n_safe
    f = np.where(n2 < EPS_EXP**2, f_series, f_gen)
    return f[..., None] * qv


def mul(q1: FloatArray, q2: FloatArray) -> FloatArray:
    """Hamilton product ``q1 ⊗ q2`` (rotation q2 first, then q1).

    Args:
        q1: (..., 4) quaternion.
        q2: (..., 4) quaternion.

    Returns:
        (..., 4) quaternion.
    """
    q1 = as_float_array(q1, "q1", 4)
    q2 = as_float_array(q2, "q2", 4)
    v1, w1 = q1[..., :3], q1[..., 3:]
    v2, w2 = q2[..., :3], q2[..., 3:]
    v = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    w = w1 * w2 - np.sum(v1 * v2, axis=-1, keepdims=True)
    return np.concatenate([v, w], axis=-1)


def conj(q: FloatArray) -> FloatArray:
    """Conjugate ``[-q_v, w]``, the inverse of a unit quaternion.

    Args:
        q: (..., 4) quaternion.

    Returns:
        (..., 4) quaternion.
    """
    q = as_float_array(q, "q", 4)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def act(q: FloatArray, X: FloatArray) -> FloatArray:
    """Rotate points, ``Y = R(q) X``.

    Upstream: gn_kernels.cu::actSO3.

        u = 2 q_v x X,   Y = X + w u + q_v x u

    Args:
        q: (..., 4) unit quaternion.
        X: (..., 3) points.

    Returns:
        (..., 3) rotated points.
    """
    q = as_float_array(q, "q", 4)
    X = as_float_array(X, "X", 3)
    qv, w = q[..., :3], q[..., 3:]
    u = 2.0 * np.cross(qv, X)
    return X + w * u + np.cross(qv, u)


def to_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrix of a unit quaternion.

    Args:
        q: (..., 4) unit quaternion.

    Returns:
        (..., 3, 3) rotation matrix R with R X = act(q, X).
    """
    q = as_float_array(q, "q", 4)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def from_matrix(R: FloatArray) -> FloatArray:
    """Unit quaternion (with w >= 0) of a rotation matrix.

    Uses the largest-pivot branch of Shepperd's method per element, so it is accurate for
    every rotation including angles near pi.

    Args:
        R: (..., 3, 3) rotation matrix.

    Returns:
        (..., 4) unit quaternion [qx, qy, qz, qw].
    """
    m = as_float_array(R, "R", (3, 3))
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Candidate quaternions (unnormalised, each accurate when its pivot is largest).
    cands = np.stack(
        [
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                    1.0 + tr,
                ],
                -1,
            ),
            np.stack(
                [
                    1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 2, 1] - m[..., 1, 2],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 1] + m[..., 1, 0],
                    1.0 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
                    m[..., 1, 2] + m[..., 2, 1],
                    m[..., 0, 2] - m[..., 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1.0 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4)
    pivots = np.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0.0, -q, q)
