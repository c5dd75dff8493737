"""Paper §3.3 — Robust weights for iteratively re-weighted least squares (IRLS).

Tracking and the backend whiten every residual component by its sqrt information and then
down-weight large whitened residuals with a Huber weight, applied **per component** (not per
pixel), as upstream does (tracker.py::solve, gn_kernels.cu with the constant 1.345 hard-coded).
A Tukey (biweight) weight is provided for experiments; upstream does not use it.

Public functions, in reading order:
    huber_weight, tukey_weight
"""

from __future__ import annotations

import numpy as np

from mslam_ref.conventions import FloatArray, as_float_array

__all__ = ["HUBER_K", "huber_weight", "tukey_weight"]

#: Huber threshold of tracking (``tracking.huber``) and of the backend (hard-coded in CUDA).
HUBER_K = 1.345


def _check_k(k: float, name: str) -> float:
    k = float(k)
    if not np.isfinite(k) or k <= 0.0:
        raise ValueError(f"{name}: must be a positive finite number, got {k}")
    return k


def huber_weight(r: FloatArray, k: float = HUBER_K) -> FloatArray:
    """IRLS weight of the Huber loss, element-wise.

    Paper: §3.3 (robust IRLS). Upstream: mast3r_slam/nonlinear_optimizer.py::huber,
    gn_kernels.cu::huber.

        w(r) = 1          if |r| < k
             = k / |r|    otherwise

    Multiplying a whitened residual's squared sqrt information by ``w`` gives the Huber
    loss's first-order IRLS system.

    Args:
        r: (...) whitened residuals (any shape).
        k: threshold > 0 (default 1.345, 95 % efficiency for Gaussian noise).

    Returns:
        (...) weights in (0, 1].
    """
    r = as_float_array(r, "r")
    k = _check_k(k, "k")
    a = np.abs(r)
    return np.where(a < k, 1.0, k / np.maximum(a, k))


def tukey_weight(r: FloatArray, c: float = 4.6851) -> FloatArray:
    """IRLS weight of Tukey's biweight loss, element-wise (not used upstream).

        w(r) = (1 - (r/c)^2)^2    if |r| < c
             = 0                  otherwise

    Args:
        r: (...) whitened residuals.
        c: threshold > 0 (default 4.6851, 95 % efficiency).

    Returns:
        (...) weights in [0, 1].
    """
    r = as_float_array(r, "r")
    c = _check_k(c, "c")
    u = r / c
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
