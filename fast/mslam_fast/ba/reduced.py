"""Taichi twin of ``mslam_ref.ba.reduced.factor_solve`` — same name, parameters and result.

The reduced matrix's storage (LAPACK band form or dense) is filled by one kernel that writes every
entry of it (parallel over the storage entries, each gathering its value from S or writing 0),
into an array recycled between trials (``mslam_fast._recycle``); the band storage is laid out
column-major, as LAPACK reads it, so it is factored in place with no copy. The factorisation and
the solve are LAPACK's (``dpbtrf``/``dpbtrs`` or ``dpotrf``/``dpotrs``), as in the reference, so
the result equals it. ``analyse`` has no kernel: the LM driver calls the reference's.
"""

import weakref
from typing import Any

import numpy as np
import scipy.linalg
import taichi as ti

from mslam_fast._recycle import output
from mslam_fast._runtime import ensure_init
from mslam_fast._types import nd
from mslam_ref.ba.reduced import ReducedSymbolic

__all__ = ["factor_solve"]

Array = np.ndarray[Any, Any]

#: Per analysed pattern: for each storage entry, the flat index into S of its value (-1: zero).
_GATHER: "weakref.WeakKeyDictionary[ReducedSymbolic, Array]" = weakref.WeakKeyDictionary()


@ti.kernel
def _fill_k(S: nd, gather: nd, A: nd):
    for k in range(A.shape[0]):
        g = gather[k]
        A[k] = ti.select(g >= 0, ti.cast(S[ti.max(g, 0)], ti.f64), 0.0)


def _gather(sym: ReducedSymbolic) -> Array:
    """The gather map of ``sym``'s storage, in the order the storage is filled: column-major
    ``(kd + 1, n)`` for the band, row-major ``(n, n)`` for the dense matrix (made once)."""
    g = _GATHER.get(sym)
    if g is None:
        g = np.full(sym.shape[0] * sym.shape[1], -1, np.int64)
        dst = sym.dst
        if sym.kind == "banded":  # (row, col) of the (kd + 1, n) storage, stored column-major
            dst = (dst % sym.n) * (sym.kd + 1) + dst // sym.n
        g[dst] = sym.src
        _GATHER[sym] = g
    return g


def factor_solve(symbolic: ReducedSymbolic, S: Any, rhs: Any) -> Array | None:
    """Taichi twin of ``mslam_ref.ba.reduced.factor_solve`` (storage filled by a kernel over its
    entries, factored in place by LAPACK in float64)."""
    sym, d = symbolic, symbolic.cam_dof
    S = np.ascontiguousarray(S)
    rhs = np.asarray(rhs, np.float64)
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(rhs))):
        return None
    ensure_init()
    rows, cols = sym.shape
    flat = output("reduced_storage", (rows * cols,), np.float64)
    if flat.size:
        _fill_k(S.reshape(-1), _gather(sym), flat)
    b = rhs[sym.perm].reshape(-1)
    try:
        if sym.kind == "banded":
            ab = flat.reshape(cols, rows).T  # (kd + 1, n), column-major: LAPACK's own layout
            c = scipy.linalg.cholesky_banded(ab, lower=False, overwrite_ab=True, check_finite=False)
            y = scipy.linalg.cho_solve_banded((c, False), b, check_finite=False)
        else:
            A = flat.reshape(rows, cols)
            cf = scipy.linalg.cho_factor(A, lower=False, overwrite_a=True, check_finite=False)
            y = scipy.linalg.cho_solve(cf, b, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(y)):
        return None
    return y.reshape(-1, d)[sym.inv_perm]
