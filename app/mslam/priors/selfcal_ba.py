"""Bundle adjustment with one unknown camera shared by every view: the self-calibration's solver.

The multi-view self-calibration (:mod:`mslam.priors.twoview_selfcal`) reconstructs a window of
video and then lets the camera itself vary: one focal length and one radial coefficient for
all views, beside each view's pose and each track's point. A view ``v`` maps a world point
``X`` into its frame by ``X_c = R_v X + t_v``; the image point, in units of the image's half
diagonal ``s`` about its centre ``c`` (the units of :mod:`mslam.datasets.images`), is

    x_u = F · (X_c,x / X_c,z, X_c,y / X_c,z)          F = f / s (focal length over half diagonal)
    x_d = x_u · (1 + k |x_u|²)                        one radial coefficient k, forward model
    e   = (uv − c) − s · x_d                           residual in pixels, where it was measured

The residual is taken in the observed (distorted) image: measuring it after undistorting the
observations instead lets ``k`` shrink the outer residuals and biases ``F`` and ``k`` (5 % on
noise-only synthetic data). The principal point stays at the image centre.

**Solver.** Levenberg–Marquardt on the Huber cost (``HUBER_PX``), the poses updated on the
left (``R ← Exp(δω) R``, ``t ← Exp(δω) t + δt``), points and ``(log F, k)`` additively. Each
step eliminates the points (3x3 blocks) and solves the dense reduced system of the free views
and the two camera parameters: the windows here have tens of views and hundreds of points, so
the reduced matrix is small and dense algebra beats sparse. ``anchor`` views stay fixed (the
gauge's pose); the scale's gauge is left to the damping, which does not touch ``F`` or ``k``
(both are invariant under it).

**Uncertainty.** :func:`camera_covariance` is the marginal covariance of ``(log F, k)`` for
unit pixel noise: the inverse of the undamped reduced system's Schur complement onto those
two (a pseudo-inverse over the views, whose scale gauge is singular).

Public names, in reading order:
    HUBER_PX, Problem, Solution, residuals, bundle_adjust, camera_covariance
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mslam_ref import so3
from mslam_ref.ba.robust import RobustKernel, rho_and_weight
from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["HUBER_PX", "Problem", "Solution", "bundle_adjust", "camera_covariance", "residuals"]

#: Residuals beyond this many pixels are weighted down (Huber).
HUBER_PX = 1.0
_HUBER = RobustKernel("huber", HUBER_PX)


@dataclass(frozen=True)
class Problem:
    """Observations of one window (O observations, V views, P points).

    Attributes:
        view: (O,) view of each observation. point: (O,) its point.
        uv: (O, 2) observed pixels.
        c: (2,) image centre (pixels). s: half diagonal (pixels).
    """

    view: IntArray
    point: IntArray
    uv: FloatArray
    c: FloatArray
    s: float


@dataclass(frozen=True)
class Solution:
    """Poses, points and the shared camera.

    Attributes:
        R: (V, 3, 3) world-to-camera rotations. t: (V, 3) translations.
        X: (P, 3) points. F: focal length over the half diagonal. k: radial coefficient.
    """

    R: FloatArray
    t: FloatArray
    X: FloatArray
    F: float
    k: float


def residuals(p: Problem, x: Solution) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(e (O, 2) pixels, X_c (O, 3), x_u (O, 2))`` of the module docstring's model."""
    X_c = (x.R[p.view] @ x.X[p.point][:, :, None])[:, :, 0] + x.t[p.view]
    x_u = x.F * X_c[:, :2] / X_c[:, 2:3]
    x_d = x_u * (1.0 + x.k * (x_u * x_u).sum(1, keepdims=True))
    return (p.uv - p.c) - p.s * x_d, X_c, x_u


def _huber(e: FloatArray) -> tuple[float, FloatArray]:
    """Huber cost (``½ Σ ρ``) and IRLS weights (O,) of residual vectors e (O, 2)."""
    rho, w = rho_and_weight((e * e).sum(1), _HUBER)
    return 0.5 * float(rho.sum()), w


def _jacobians(p: Problem, x: Solution, X_c: FloatArray, x_u: FloatArray):
    """Per observation: d e / d[δω, δt] (O, 2, 6), d e / d[log F, k] (O, 2, 2), d e / dX (O, 2, 3)."""
    O = len(X_c)
    iz = 1.0 / X_c[:, 2]
    dpi = np.zeros((O, 2, 3))  # d(X/Z, Y/Z)/dX_c
    dpi[:, 0, 0] = dpi[:, 1, 1] = iz
    dpi[:, 0, 2] = -X_c[:, 0] * iz * iz
    dpi[:, 1, 2] = -X_c[:, 1] * iz * iz
    r2 = (x_u * x_u).sum(1)
    A = (1.0 + x.k * r2)[:, None, None] * np.eye(2) + 2.0 * x.k * x_u[:, :, None] * x_u[:, None, :]
    de_dXc = -p.s * x.F * (A @ dpi)  # (O, 2, 3)
    J_pose = np.concatenate([de_dXc @ -so3.hat(X_c), de_dXc], axis=2)
    J_cam = np.stack([-p.s * (A @ x_u[:, :, None])[:, :, 0], -p.s * x_u * r2[:, None]], axis=2)
    J_pt = de_dXc @ x.R[p.view]
    return J_pose, J_cam, J_pt


def _sum_by(index: IntArray, values: FloatArray, n: int) -> FloatArray:
    """``values`` (O, ...) summed by ``index`` (O,) into (n, ...)."""
    flat = values.reshape(len(values), -1)
    cols = flat.shape[1]
    idx = (index[:, None] * cols + np.arange(cols)).ravel()
    return np.bincount(idx, flat.ravel(), n * cols).reshape((n, *values.shape[1:]))


def _normal_equations(p: Problem, x: Solution, free: IntArray, camera: bool):
    """Weighted normal equations: ``(U (C, C), b_c (C,), W (C, P, 3), V (P, 3, 3), b_p (P, 3),
    cost)`` with C = 6 · (free views) + 2 (the camera; zero rows when it is fixed)."""
    e, X_c, x_u = residuals(p, x)
    cost, w = _huber(e)
    J_pose, J_cam, J_pt = _jacobians(p, x, X_c, x_u)
    sw = np.sqrt(w)[:, None, None]
    J_c = np.concatenate([J_pose, J_cam if camera else 0.0 * J_cam], axis=2) * sw  # (O, 2, 8)
    J_pt, e = J_pt * sw, e * sw[:, :, 0]
    nV, P = len(free), len(x.X)
    C = 6 * nV + 2
    slot = np.full(len(x.R), -1)
    slot[free] = np.arange(nV)
    sv = slot[p.view]
    idx = np.where(sv[:, None] >= 0, 6 * sv[:, None] + np.arange(6), C)  # fixed views: dummy C
    idx = np.concatenate([idx, np.broadcast_to([C - 2, C - 1], (len(sv), 2))], axis=1)
    U = np.bincount((idx[:, :, None] * (C + 1) + idx[:, None, :]).ravel(),
                    (J_c.transpose(0, 2, 1) @ J_c).ravel(), (C + 1) ** 2)  # fmt: skip
    b_c = np.bincount(idx.ravel(), (J_c.transpose(0, 2, 1) @ e[:, :, None]).ravel(), C + 1)[:C]
    W = np.bincount((idx[:, :, None] * (3 * P) + 3 * p.point[:, None, None] + np.arange(3)).ravel(),
                    (J_c.transpose(0, 2, 1) @ J_pt).ravel(), (C + 1) * 3 * P)  # fmt: skip
    V = _sum_by(p.point, J_pt.transpose(0, 2, 1) @ J_pt, P)
    b_p = _sum_by(p.point, (J_pt.transpose(0, 2, 1) @ e[:, :, None])[:, :, 0], P)
    U = U.reshape(C + 1, C + 1)[:C, :C]
    return U, b_c, W.reshape(C + 1, P, 3)[:C], V, b_p, cost


def _schur(U, W, V_inv):
    """Reduced matrix ``U − W V⁻¹ Wᵀ`` (C, C) and ``Y = W V⁻¹`` (C, P, 3)."""
    Y = (W.transpose(1, 0, 2) @ V_inv).transpose(1, 0, 2)
    C = len(U)
    return U - Y.reshape(C, -1) @ W.reshape(C, -1).T, Y


def _step(x: Solution, free: IntArray, d_c: FloatArray, d_X: FloatArray, camera: bool) -> Solution:
    """``x`` moved by the increments of the free views, the camera and the points."""
    R, t = x.R.copy(), x.t.copy()
    d = d_c[: 6 * len(free)].reshape(-1, 6)
    dR = so3.to_matrix(so3.exp(d[:, :3]))
    R[free] = dR @ x.R[free]
    t[free] = np.einsum("vij,vj->vi", dR, x.t[free]) + d[:, 3:]
    F, k = (x.F * np.exp(d_c[-2]), x.k + d_c[-1]) if camera else (x.F, x.k)
    return Solution(R, t, x.X + d_X, float(F), float(k))


def bundle_adjust(
    p: Problem,
    x: Solution,
    anchor: IntArray,
    camera: bool = True,
    iterations: int = 30,
    tol: float = 1e-7,
) -> tuple[Solution, float]:
    """Levenberg–Marquardt over the poses (all but ``anchor``), the points and, with ``camera``,
    ``(F, k)``; returns the solution and its Huber cost. Observations must lie in front of
    their views (``X_c,z > 0``); a step that moves one behind is refused like one that raises
    the cost. Stops after ``iterations`` or when a step lowers the cost by less than ``tol``
    of it."""
    free = np.setdiff1d(np.arange(len(x.R)), anchor)
    mu = None
    U, b_c, W, V, b_p, cost = _normal_equations(p, x, free, camera)
    for _ in range(iterations):
        if mu is None:
            mu = 1e-4 * max(float(np.max(np.diag(U), initial=0.0)), float(V.trace(0, 1, 2).max()))
        while True:
            Va = V + (mu * np.einsum("pii->pi", V) + 1e-12)[:, :, None] * np.eye(3)
            Va_inv = np.linalg.inv(Va)
            Ua = U + mu * np.diag(np.maximum(np.diag(U), 1e-9))
            S, Y = _schur(Ua, W, Va_inv)
            rhs = -b_c + Y.reshape(len(U), -1) @ b_p.ravel()
            try:
                d_c = np.linalg.solve(S + 1e-12 * np.eye(len(S)), rhs)
            except np.linalg.LinAlgError:
                d_c = np.linalg.lstsq(S, rhs, rcond=None)[0]
            d_X = np.einsum("pkl,pl->pk", Va_inv, -b_p - np.einsum("cpk,c->pk", W, d_c))
            x_new = _step(x, free, d_c, d_X, camera)
            e, X_c, _ = residuals(p, x_new)
            new_cost = _huber(e)[0] if np.all(X_c[:, 2] > 0) else np.inf
            if new_cost < cost:
                break
            mu *= 4.0
            if mu > 1e12:
                return x, cost
        gain = (cost - new_cost) / max(cost, 1e-300)
        x, mu = x_new, max(mu / 3.0, 1e-12)
        U, b_c, W, V, b_p, cost = _normal_equations(p, x, free, camera)
        if gain < tol:
            break
    return x, cost


def camera_covariance(p: Problem, x: Solution, anchor: IntArray) -> FloatArray:
    """(2, 2) covariance of ``(log F, k)`` for unit pixel noise (module docstring); infinite
    where the observations leave some combination of the two undetermined."""
    free = np.setdiff1d(np.arange(len(x.R)), anchor)
    U, _, W, V, _, _ = _normal_equations(p, x, free, True)
    S, _ = _schur(U, W, np.linalg.pinv(V))
    A, B, D = S[:-2, :-2], S[:-2, -2:], S[-2:, -2:]
    info = D - B.T @ np.linalg.pinv(A, rcond=1e-10, hermitian=True) @ B
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    if w.min() <= 1e-12 * max(w.max(), 1e-300):  # no information on some combination
        return np.full((2, 2), np.inf)
    return (V / w) @ V.T
