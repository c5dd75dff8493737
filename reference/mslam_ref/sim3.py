"""Paper §3.1 — Sim(3): similarity transforms, the pose group of MASt3R-SLAM.

Layout (lietorch / upstream, so that upstream dumps compare directly):

* a group element is ``T = [tx, ty, tz, qx, qy, qz, qw, s]`` of shape ``(..., 8)``: translation,
  unit Hamilton quaternion in xyzw order, and the scale ``s > 0`` stored directly (not its log);
* its matrix is ``[[s R, t], [0, 1]]`` and it acts on points as ``T · X = s R X + t``;
* a tangent vector is ``xi = [tau, phi, sigma]`` of shape ``(..., 7)``: translation part, rotation
  vector, log-scale (lietorch and Sophus order), with
  ``hat(xi) = [[phi^ + sigma I, tau], [0, 0]]``;
* perturbations are on the **left**: ``retract(T, xi) = Exp(xi) · T`` (paper Eq. 1, lietorch
  ``retr``).

Every function broadcasts over leading batch axes and works in float64. Inputs are checked:
a wrong trailing shape, a NaN or inf, or a non-positive scale raises ``ValueError`` naming the
argument. Quaternions are normalised on input, as lietorch does when it builds an element
(upstream's CUDA retraction does not re-normalise; see ``retract``).

Public functions, in reading order:
    identity, exp, log, mul, inv, act, act_and_jacobian, adjoint, adjoint_inv_apply,
    retract, to_matrix, from_matrix, validate

Upstream: lietorch include/sim3.h and rxso3.h (Exp, Log, Adj, calcW), mast3r_slam
backend/src/gn_kernels.cu (expSim3, relSim3, actSim3, apply_Sim3_adj_inv, pose_retr_kernel).
"""

from __future__ import annotations

import numpy as np

from mslam_ref import so3
from mslam_ref.conventions import (
    EPS_EXP,
    SIM3_IDENTITY,
    FloatArray,
    as_float_array,
    sim3_tangent,
)

# fmt: off
__all__ = [  # in reading order
    "identity", "exp", "log", "mul", "inv", "act", "act_and_jacobian",
    "adjoint", "adjoint_inv_apply", "retract", "to_matrix", "from_matrix", "validate",
]
# fmt: on


def validate(T: FloatArray, name: str = "T") -> FloatArray:
    """Check a Sim(3) array and return it with its quaternion normalised.

    Args:
        T: (..., 8) Sim(3) element(s).
        name: argument name used in error messages.

    Returns:
        (..., 8) float64 copy with a unit quaternion.

    Raises:
        ValueError: wrong trailing shape, NaN/inf, s <= 0, or a zero quaternion.
    """
    T = as_float_array(T, name, 8)
    if np.any(T[..., 7] <= 0.0):
        raise ValueError(f"{name}: scale s (index 7) must be positive")
    return np.concatenate([T[..., :3], so3.normalize(T[..., 3:7], name), T[..., 7:]], axis=-1)


def _broadcast_last(*arrays: FloatArray) -> list[FloatArray]:
    """Broadcast the leading (batch) axes of arrays that differ in their last axis."""
    batch = np.broadcast_shapes(*(a.shape[:-1] for a in arrays))
    return [np.broadcast_to(a, (*batch, a.shape[-1])) for a in arrays]


def _split(T: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    return T[..., :3], T[..., 3:7], T[..., 7:8]


def identity(batch_shape: tuple[int, ...] = ()) -> FloatArray:
    """Identity elements ``[0, 0, 0, 0, 0, 0, 1, 1]``.

    Args:
        batch_shape: leading shape of the result.

    Returns:
        (*batch_shape, 8) array.
    """
    return np.broadcast_to(SIM3_IDENTITY, (*tuple(batch_shape), 8)).copy()


def _W_coefficients(phi: FloatArray, sigma: FloatArray) -> tuple[FloatArray, ...]:
    """Coefficients A, B, C of ``W = A Phi + B Phi^2 + C I`` (lietorch rxso3.h::calcW).

    ``t = W tau`` in Exp. Branches (EPS = 1e-6), with theta = ||phi||, s = e^sigma:
        |sigma| < EPS: C = 1;  theta < EPS: A = 1/2, B = 1/6
                               else A = (1 - cos th)/th^2, B = (th - sin th)/th^3
        |sigma| >= EPS: C = (s - 1)/sigma
            theta < EPS: A = ((sigma - 1)s + 1)/sigma^2, B = (s sigma^2/2 + s - 1 - sigma s)/sigma^3
            else, a = s sin th, b = s cos th, c = th^2 + sigma^2:
                A = (a sigma + (1 - b) th)/(th c),  B = (C - ((b - 1) sigma + a th)/c)/th^2
    lietorch keeps only the sigma^0 terms when |sigma| < EPS, an error of up to sigma/2 * |tau|
    (5e-7 relative); the sigma terms above (from W = int_0^1 e^(sigma u) Exp_SO3(u phi) du)
    make the reference accurate to ~1e-12. C uses ``expm1(sigma)/sigma``: the literal
    ``(s - 1)/sigma`` loses up to 1e-10 relative just above sigma = EPS. Division by zero is
    avoided by evaluating every branch on safe stand-in values.
    """
    th = np.linalg.norm(phi, axis=-1)
    small_th = th < EPS_EXP
    small_sg = np.abs(sigma) < EPS_EXP
    th_ = np.where(small_th, 1.0, th)  # safe stand-ins
    sg_ = np.where(small_sg, 1.0, sigma)
    s_ = np.exp(sg_)
    # sigma ~ 0
    cos, sin = np.cos(th_), np.sin(th_)
    # 1 - cos = 2 sin^2(th/2) without cancellation (the literal form loses 1e-4 relative at 1e-6)
    A0 = np.where(
        small_th,
        0.5 + sigma / 3.0,
        2.0 * np.sin(0.5 * th_) ** 2 / th_**2 + sigma * (sin - th_ * cos) / th_**3,
    )
    B0 = np.where(
        small_th,
        1.0 / 6.0,
        (th_ - sin) / th_**3 + sigma * (0.5 / th_**2 - (cos + th_ * sin - 1.0) / th_**4),
    )
    # sigma != 0
    C1 = np.expm1(sg_) / sg_  # (s - 1)/sigma loses ~1e-10 relative at sigma ~ 1e-6
    # theta < EPS: A = int_0^1 u e^(sigma u) du, B = int_0^1 u^2/2 e^(sigma u) du. The closed forms
    # cancel for small sigma (relative error 1e-16/sigma^2), so |sigma| < 1e-2 uses the series.
    ser = np.abs(sg_) < 1e-2
    A1_small = np.where(
        ser,
        0.5 + sg_ / 3.0 + sg_**2 / 8.0 + sg_**3 / 30.0 + sg_**4 / 144.0,
        ((sg_ - 1.0) * s_ + 1.0) / sg_**2,
    )
    B1_small = np.where(
        ser,
        1.0 / 6.0 + sg_ / 8.0 + sg_**2 / 20.0 + sg_**3 / 72.0 + sg_**4 / 336.0,
        (s_ * sg_**2 / 2.0 + s_ - 1.0 - sg_ * s_) / sg_**3,
    )
    a, b, c = s_ * np.sin(th_), s_ * np.cos(th_), th_**2 + sg_**2
    A1 = (a * sg_ + (1.0 - b) * th_) / (th_ * c)
    B1 = (C1 - ((b - 1.0) * sg_ + a * th_) / c) / th_**2
    A = np.where(small_sg, A0, np.where(small_th, A1_small, A1))
    B = np.where(small_sg, B0, np.where(small_th, B1_small, B1))
    C = np.where(small_sg, 1.0 + sigma / 2.0 + sigma**2 / 6.0, C1)
    return A, B, C


def _W_matrix(phi: FloatArray, sigma: FloatArray) -> FloatArray:
    """``W = A Phi + B Phi^2 + C I`` of shape (..., 3, 3)."""
    A, B, C = _W_coefficients(phi, sigma)
    Phi = so3.hat(phi)
    eye = np.eye(3)
    return A[..., None, None] * Phi + B[..., None, None] * (Phi @ Phi) + C[..., None, None] * eye


def exp(xi: FloatArray) -> FloatArray:
    """Exponential map, tangent ``[tau, phi, sigma]`` to ``[t, q, s]``.

    Paper: §3.1, Eq. (1) context. Upstream: lietorch sim3.h::Exp, gn_kernels.cu::expSim3.

        q = Exp_SO3(phi),  s = e^sigma,  t = W(phi, sigma) tau
        W = A [phi]x + B [phi]x^2 + C I     (coefficients in ``_W_coefficients``)

    Numerics: series for theta < 1e-6 and |sigma| < 1e-6 as lietorch; |sigma| >= 690 is a
    ``ValueError`` (e^sigma overflows), as in the fast twin.

    Args:
        xi: (..., 7) tangent vector [tau (3), phi (3), sigma (1)].

    Returns:
        (..., 8) Sim(3) element.
    """
    xi = sim3_tangent(xi, "xi")
    tau, phi, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6]
    W = _W_matrix(phi, sigma)
    t = np.einsum("...ij,...j->...i", W, tau)
    return np.concatenate([t, so3.exp(phi), np.exp(sigma)[..., None]], axis=-1)


def log(T: FloatArray) -> FloatArray:
    """Logarithm map, ``[t, q, s]`` to ``[tau, phi, sigma]`` with ``||phi|| <= pi``.

    Upstream: lietorch sim3.h::Log (tooling only; never used in the SLAM loop).

        phi = Log_SO3(q),  sigma = log s,  tau = W(phi, sigma)^-1 t

    Args:
        T: (..., 8) Sim(3) element.

    Returns:
        (..., 7) tangent vector.
    """
    T = validate(T)
    t, q, s = _split(T)
    phi = so3.log(q)
    sigma = np.log(s[..., 0])
    tau = np.linalg.solve(_W_matrix(phi, sigma), t[..., None])[..., 0]
    return np.concatenate([tau, phi, sigma[..., None]], axis=-1)


def mul(A: FloatArray, B: FloatArray) -> FloatArray:
    """Composition ``A ∘ B`` (apply B first).

    Upstream: lietorch sim3.h::operator*.

        (s1 R1, t1) ∘ (s2 R2, t2) = (s1 s2, q1 ⊗ q2, t1 + s1 R1 t2)

    Args:
        A: (..., 8) Sim(3) element.
        B: (..., 8) Sim(3) element.

    Returns:
        (..., 8) Sim(3) element, broadcast over the leading axes of A and B.
    """
    A, B = validate(A, "A"), validate(B, "B")
    tA, qA, sA = _split(A)
    tB, qB, sB = _split(B)
    t = tA + sA * so3.act(qA, tB)
    return np.concatenate(_broadcast_last(t, so3.mul(qA, qB), sA * sB), axis=-1)


def inv(T: FloatArray) -> FloatArray:
    """Inverse ``(1/s, q*, -(1/s) R^T t)``.

    Args:
        T: (..., 8) Sim(3) element.

    Returns:
        (..., 8) Sim(3) element.
    """
    T = validate(T)
    t, q, s = _split(T)
    qi = so3.conj(q)
    return np.concatenate([-so3.act(qi, t) / s, qi, 1.0 / s], axis=-1)


def act(T: FloatArray, X: FloatArray) -> FloatArray:
    """Action on points ``T · X = s R X + t``.

    Upstream: gn_kernels.cu::actSim3, lietorch act.

    Args:
        T: (..., 8) Sim(3) element.
        X: (..., 3) points.

    Returns:
        (..., 3) transformed points, broadcast over the leading axes of T and X.
    """
    T = validate(T)
    X = as_float_array(X, "X", 3)
    t, q, s = _split(T)
    return s * so3.act(q, X) + t


def act_and_jacobian(T: FloatArray, X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Action and its Jacobian with respect to a left perturbation of T.

    Paper: §3.3 (used by every residual). Upstream: geometry.py::act_Sim3(jacobian=True).

        Exp(xi) · P ≈ P + tau + phi x P + sigma P   =>   dP/dxi = [ I | -[P]x | P ]

    Args:
        T: (..., 8) Sim(3) element.
        X: (..., 3) points.

    Returns:
        P: (..., 3) transformed points.
        J: (..., 3, 7) dP/dxi.
    """
    P = act(T, X)
    eye = np.broadcast_to(np.eye(3), (*P.shape[:-1], 3, 3))
    J = np.concatenate([eye, -so3.hat(P), P[..., :, None]], axis=-1)
    return P, J


def adjoint(T: FloatArray) -> FloatArray:
    """Adjoint matrix with ``T · Exp(a) · T^-1 = Exp(adjoint(T) a)``.

    Upstream: lietorch sim3.h::Adj.

        Ad(T) = [[ s R , [t]x R , -t ],
                 [ 0   ,   R    ,  0 ],
                 [ 0   ,   0    ,  1 ]]

    Args:
        T: (..., 8) Sim(3) element.

    Returns:
        (..., 7, 7) matrix.
    """
    T = validate(T)
    t, q, s = _split(T)
    R = so3.to_matrix(q)
    Ad = np.zeros((*T.shape[:-1], 7, 7))
    Ad[..., :3, :3] = s[..., None] * R
    Ad[..., :3, 3:6] = so3.hat(t) @ R
    Ad[..., :3, 6] = -t
    Ad[..., 3:6, 3:6] = R
    Ad[..., 6, 6] = 1.0
    return Ad


def adjoint_inv_apply(T: FloatArray, J: FloatArray) -> FloatArray:
    """Row Jacobian times ``adjoint(T)^-1``, the chain rule onto a world-frame perturbation.

    Paper: §3.5 (backend Jacobians). Upstream: gn_kernels.cu::apply_Sim3_adj_inv.
    With the row J = (a, b, c) split as (3, 3, 1):

        y_tau   = (1/s) R a
        y_phi   = R b + (1/s) t x (R a)
        y_sigma = c + (1/s) t . (R a)

    Args:
        T: (..., 8) Sim(3) element.
        J: (..., 7) row Jacobian.

    Returns:
        (..., 7) the row ``J · adjoint(T)^-1``.
    """
    T = validate(T)
    J = as_float_array(J, "J", 7)
    t, q, s = _split(T)
    Ra = so3.act(q, J[..., :3])
    y_tau = Ra / s
    y_phi = so3.act(q, J[..., 3:6]) + np.cross(t, Ra) / s
    y_sigma = J[..., 6:7] + np.sum(t * Ra, axis=-1, keepdims=True) / s
    return np.concatenate(_broadcast_last(y_tau, y_phi, y_sigma), axis=-1)


def retract(T: FloatArray, xi: FloatArray) -> FloatArray:
    """Left retraction ``Exp(xi) · T``, the update rule everywhere in MASt3R-SLAM.

    Paper: Eq. (1). Upstream: lietorch retr, gn_kernels.cu::pose_retr_kernel.

        q <- dq ⊗ q,  t <- ds (dR t) + dt,  s <- ds s      with (dt, dq, ds) = Exp(xi)

    The result's quaternion is normalised (lietorch); upstream's CUDA kernel skips that.

    Args:
        T: (..., 8) Sim(3) element.
        xi: (..., 7) tangent vector.

    Returns:
        (..., 8) Sim(3) element.
    """
    T = validate(T)  # so that a bad T is reported as "T", not as mul's "B"
    out = mul(exp(xi), T)
    return np.concatenate([out[..., :3], so3.normalize(out[..., 3:7]), out[..., 7:]], axis=-1)


def to_matrix(T: FloatArray) -> FloatArray:
    """4x4 matrix ``[[s R, t], [0, 1]]``.

    Args:
        T: (..., 8) Sim(3) element.

    Returns:
        (..., 4, 4) matrix.
    """
    T = validate(T)
    t, q, s = _split(T)
    M = np.zeros((*T.shape[:-1], 4, 4))
    M[..., :3, :3] = s[..., None] * so3.to_matrix(q)
    M[..., :3, 3] = t
    M[..., 3, 3] = 1.0
    return M


def from_matrix(M: FloatArray) -> FloatArray:
    """Sim(3) element of a 4x4 similarity matrix; ``s = det(sR)^(1/3)``, quaternion w >= 0.

    Args:
        M: (..., 4, 4) matrix ``[[s R, t], [0, 1]]``.

    Returns:
        (..., 8) Sim(3) element.

    Raises:
        ValueError: when the 3x3 block has a non-positive determinant.
    """
    M = as_float_array(M, "M", (4, 4))
    sR = M[..., :3, :3]
    det = np.linalg.det(sR)
    if np.any(det <= 0.0):
        raise ValueError("M: the 3x3 block must have a positive determinant (a scaled rotation)")
    s = np.cbrt(det)
    q = so3.from_matrix(sR / s[..., None, None])
    return np.concatenate([M[..., :3, 3], q, s[..., None]], axis=-1)
