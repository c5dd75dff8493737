"""Robust refinement of a two-view pose — the small Levenberg–Marquardt of
:func:`mslam.priors.twoview_geometry.refine_pose`.

``huber_lm`` minimises ``sum huber_delta(r(p))`` over a few parameters with IRLS weights
``w = min(1, delta / |r|)``, a forward-difference Jacobian (its evaluations batched in one
call) and a step taken only when it lowers the cost; ``sampson_fn`` evaluates the Sampson
distances of M poses with the homogeneous pixels prepared once (one matrix product for all M
up to ``ONE_PRODUCT_MAX_N`` correspondences; the parameter sets' rotations in one stacked
Rodrigues, :func:`so3_exp`). Both give the numbers of one evaluation per pose, bit for bit
(tests/app/test_twoview_lm.py), and took the refinement from 6.3 to 4.3 ms per call at 600
correspondences (2026-11-29). It replaced SciPy's
``least_squares`` (same poses to < 0.01° on 7-Scenes pairs, ~5x less CPU: the solver's own
overhead dominated at a few thousand residuals).

Public names, in reading order:
    ONE_PRODUCT_MAX_N, so3_exp, sampson_fn, huber_cost_sum, huber_lm
"""

from __future__ import annotations

import numpy as np

from mslam_ref import so3
from mslam_ref.conventions import FloatArray

__all__ = ["ONE_PRODUCT_MAX_N", "huber_cost_sum", "huber_lm", "sampson_fn", "so3_exp"]


#: Largest N for which :func:`sampson_fn` evaluates all poses in one matrix product: the
#: same numbers as one product per pose (tested bit for bit), about 2x faster for 5 poses at
#: N = 600 (the hypotheses' subsample), slower above about 2000 correspondences (2026-11-29).
ONE_PRODUCT_MAX_N = 2000


def so3_exp(w: FloatArray) -> FloatArray:
    """Rodrigues: rotation vectors (..., 3) to matrices (..., 3, 3).

    Evaluated elementwise with the same operations for one vector or a stack (bit-identical
    rows); the first-order form ``I + [w]x`` below 1e-12 rad."""
    w = np.asarray(w, np.float64)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    Wx = so3.hat(w)
    small = th < 1e-12
    th = np.where(small, 1.0, th)
    full = np.eye(3) + np.sin(th) / th * Wx + (1 - np.cos(th)) / th**2 * (Wx @ Wx)
    return np.where(small, np.eye(3) + Wx, full)


def sampson_fn(uv_i: FloatArray, uv_j: FloatArray, K: FloatArray):
    """:func:`mslam.priors.twoview_geometry.sampson_residuals` of M poses at once, the
    homogeneous pixels prepared once: ``f(R (M, 3, 3), t (M, 3)) -> (M, N)``."""
    Kinv = np.linalg.inv(K)
    n = len(uv_i)
    xi = np.column_stack([np.asarray(uv_i, np.float64).reshape(n, 2), np.ones(n)])
    xj = np.column_stack([np.asarray(uv_j, np.float64).reshape(n, 2), np.ones(n)])

    def f(R: FloatArray, t: FloatArray) -> FloatArray:
        F = Kinv.T @ so3.hat(t) @ R @ Kinv
        M = len(F)
        if n <= ONE_PRODUCT_MAX_N:  # all M poses in one BLAS product: (N, 3) @ (3, 3M)
            Fxi = (xi @ F.transpose(2, 0, 1).reshape(3, 3 * M)).reshape(n, M, 3)
            Ftxj = (xj @ F.transpose(1, 0, 2).reshape(3, 3 * M)).reshape(n, M, 3)
            num = np.einsum("nk,nmk->mn", xj, Fxi)
            den = Fxi[..., 0] ** 2 + Fxi[..., 1] ** 2 + Ftxj[..., 0] ** 2 + Ftxj[..., 1] ** 2
            # C order, as the per-pose rows: the caller's products sum in memory order
            return np.ascontiguousarray(num / np.maximum(np.sqrt(den).T, 1e-12))
        out = np.empty((M, n))
        for m, Fm in enumerate(F):  # one 2-D product per pose (a stacked matmul was 2x slower)
            Fxi, Ftxj = xi @ Fm.T, xj @ Fm
            num = np.einsum("nk,nk->n", xj, Fxi)
            den = np.sqrt(Fxi[:, 0] ** 2 + Fxi[:, 1] ** 2 + Ftxj[:, 0] ** 2 + Ftxj[:, 1] ** 2)
            out[m] = num / np.maximum(den, 1e-12)
        return out

    return f


def huber_cost_sum(r: FloatArray, delta: float) -> float:
    """``sum_n huber_delta(r_n)``: ``r²/2`` below ``delta``, ``delta (|r| - delta/2)`` above."""
    a = np.abs(r)
    return float(np.sum(np.where(a < delta, 0.5 * a * a, delta * (a - 0.5 * delta))))


def huber_lm(fun, p0: FloatArray, delta: float, max_iters: int = 30, h: float = 1e-7):
    """Minimise ``sum huber_delta(fun(p))`` by Levenberg–Marquardt on IRLS weights
    ``w = min(1, delta / |r|)`` with a forward-difference Jacobian; a step is taken only when
    it lowers the cost. ``fun`` maps (M, P) parameter sets to (M, N) residuals (the Jacobian's
    P evaluations are one call). Returns p, or None when the residuals are not finite."""
    p = np.asarray(p0, np.float64).copy()
    r = fun(p[None])[0]
    if not np.all(np.isfinite(r)):
        return None
    cost, lam = huber_cost_sum(r, delta), 1e-3
    for _ in range(max_iters):
        J = ((fun(p[None] + h * np.eye(len(p))) - r[None]) / h).T  # (N, P)
        w = np.minimum(1.0, delta / np.maximum(np.abs(r), 1e-15))
        A = J.T @ (w[:, None] * J)
        g = J.T @ (w * r)
        improved = False
        while lam < 1e10:
            try:
                dp = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            r_new = fun((p + dp)[None])[0]
            c_new = huber_cost_sum(r_new, delta) if np.all(np.isfinite(r_new)) else np.inf
            if c_new < cost:
                p, r, lam, improved = p + dp, r_new, max(lam / 10, 1e-9), True
                done = cost - c_new <= 1e-10 * cost or float(np.linalg.norm(dp)) < 1e-10
                cost = c_new
                break
            lam *= 10
        if not improved or done:
            break
    return p
