"""Conventions shared by every module: array aliases, dimension letters, input checks.

Dimension letters used in docstrings (see docs/conventions.md):
    H, W   image height and width in pixels (network output resolution)
    N      H * W pixels of one image, or the number of points in a flat list
    F      descriptor dimension (24 for MASt3R)
    K      number of keyframes
    E      number of graph edges
    M, P   bundle adjustment: number of cameras (poses) and of points (landmarks)
    O      bundle adjustment: number of observations (edges)

Frames: ``T_AB`` maps points expressed in frame B into frame A (``X_A = T_AB · X_B``).
Pixels are ``(u, v) = (column, row)``; the linear pixel index is ``n = u + W v``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
U32Array = npt.NDArray[np.uint32]

#: Threshold of the small-angle / small-sigma series in Exp and Log (lietorch's EPS).
EPS_EXP = 1e-6

#: Identity element of Sim(3) in data layout [tx, ty, tz, qx, qy, qz, qw, s].
SIM3_IDENTITY = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0])


def as_float_array(x: Any, name: str, trailing: int | tuple[int, ...] | None = None) -> FloatArray:
    """Convert ``x`` to a float64 array and check its trailing shape and finiteness.

    Args:
        x: array-like input.
        name: argument name used in error messages.
        trailing: required trailing dimension(s), e.g. ``3`` or ``(3, 3)``; None skips the check.

    Returns:
        float64 array (a copy only when conversion needs one).

    Raises:
        ValueError: on a boolean or non-numeric input, a wrong trailing shape or a NaN/inf
            entry, naming ``name``.
    """
    raw = np.asarray(x)
    if raw.dtype == np.bool_:
        raise ValueError(f"{name}: expected numbers, got a boolean array")
    arr = np.asarray(raw, dtype=np.float64)
    if trailing is not None:
        tr = (trailing,) if isinstance(trailing, int) else tuple(trailing)
        if arr.ndim < len(tr) or arr.shape[arr.ndim - len(tr) :] != tr:
            raise ValueError(f"{name}: expected trailing shape {tr}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains non-finite values (NaN or inf)")
    return arr


def as_points(x: Any, name: str, n: int | None = None) -> FloatArray:
    """A flat ``(N, 3)`` float64 view of points given as ``(..., 3)``, optionally checking N.

    Raises:
        ValueError: wrong trailing shape, non-finite values or (with ``n``) a wrong count.
    """
    X = as_float_array(x, name, 3).reshape(-1, 3)
    if n is not None and len(X) != n:
        raise ValueError(f"{name}: expected {n} points, got {len(X)}")
    return X


def as_flat_bool(x: Any, name: str, n: int | None = None) -> BoolArray:
    """A flat boolean mask; 0/1 numbers are accepted, anything else raises (naming ``name``)."""
    a = np.asarray(x)
    if a.dtype != np.bool_:
        if not np.issubdtype(a.dtype, np.number) or not np.all(np.isin(a, (0, 1))):
            raise ValueError(f"{name}: expected a boolean mask")
        a = a.astype(bool)
    a = a.reshape(-1)
    if n is not None and len(a) != n:
        raise ValueError(f"{name}: expected {n} entries, got {len(a)}")
    return a


def as_flat_float(x: Any, name: str, n: int | None = None, nonneg: bool = False) -> FloatArray:
    """A flat finite float64 array, optionally of length ``n`` and non-negative."""
    a = as_float_array(x, name).reshape(-1)
    if n is not None and len(a) != n:
        raise ValueError(f"{name}: expected {n} entries, got {len(a)}")
    if nonneg and np.any(a < 0.0):
        raise ValueError(f"{name}: must be non-negative")
    return a


def as_flat_index(x: Any, name: str, n_max: int) -> IntArray:
    """A flat int64 array of indices in ``[0, n_max)`` (integer dtype required)."""
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name}: expected integer pixel indices, got dtype {a.dtype}")
    a = a.reshape(-1).astype(np.int64)
    if len(a) and (a.min() < 0 or a.max() >= n_max):
        raise ValueError(f"{name}: indices must lie in [0, {n_max})")
    return a


#: Largest |sigma| of a Sim(3) tangent (log-scale) accepted by ``exp``/``retract`` in float64:
#: e^710 overflows and the W coefficients (e^sigma sigma^2) overflow near 697; a scale factor
#: of e^690 is far beyond any meaningful update.
SIM3_SIGMA_MAX = 690.0


def sim3_tangent(xi: Any, name: str = "xi", sigma_max: float = SIM3_SIGMA_MAX) -> FloatArray:
    """``as_float_array(xi, name, 7)`` plus ``|sigma| < sigma_max`` (sigma = index 6), so that
    ``s = e^sigma`` stays finite and positive; the same error from the reference and fast."""
    arr = as_float_array(xi, name, 7)
    big = np.abs(arr[..., 6]) >= sigma_max
    if np.any(big):
        worst = float(arr[..., 6][big].flat[0])
        raise ValueError(
            f"{name}: |sigma| (index 6) must be below {sigma_max:g} (e^sigma would overflow or "
            f"vanish), got {worst:g}"
        )
    return arr


def pixel_to_lin(u: npt.ArrayLike, v: npt.ArrayLike, W: int) -> IntArray:
    """Linear pixel index ``n = u + W v`` (upstream matching.py::pixel_to_lin)."""
    return (np.asarray(u, dtype=np.int64) + W * np.asarray(v, dtype=np.int64)).astype(np.int64)


def lin_to_pixel(n: npt.ArrayLike, W: int) -> tuple[IntArray, IntArray]:
    """Inverse of :func:`pixel_to_lin`: ``(u, v) = (n mod W, n div W)``."""
    n = np.asarray(n, dtype=np.int64)
    return n % W, n // W
