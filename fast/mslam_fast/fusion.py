"""Taichi twin of ``mslam_ref.fusion`` — same names, parameters and shapes; see there for the
maths.

``update_pointmap``: the per-pixel modes (``weighted_pointmap``, ``weighted_spherical``,
``indep_conf``) run as one parallel loop over pixels (no reduction); ``recent``, ``first`` and
``best_score`` only copy whole arrays (and take a median), so they stay on the host. Arrays of
the returned state are in the runtime float type. Config, state, ``init_pointmap`` and
``average_confidence`` have no kernel: use ``mslam_ref.fusion``'s.
"""

from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._kernels import fusion as KF
from mslam_fast._runtime import ensure_init
from mslam_fast._types import nd, template
from mslam_ref import fusion as ref_fusion
from mslam_ref.fusion import FusionConfig, PointmapState

__all__ = ["update_pointmap"]

Array = np.ndarray[Any, Any]

_KERNEL_MODES = {"weighted_pointmap": 0, "weighted_spherical": 1, "indep_conf": 2}


@ti.kernel
def _fuse_k(Xs: nd, Cs: nd, X: nd, C: nd, Xo: nd, Co: nd, mode: template):
    for n in range(Xs.shape[0]):
        a = ti.Vector([Xs[n, 0], Xs[n, 1], Xs[n, 2]])
        b = ti.Vector([X[n, 0], X[n, 1], X[n, 2]])
        ca, cb = Cs[n], C[n]
        out = a
        cout = ca
        if ti.static(mode == 0):
            out = (ca * a + cb * b) / (ca + cb)
            cout = ca + cb
        elif ti.static(mode == 1):
            out = KF.from_spherical((ca * KF.to_spherical(a) + cb * KF.to_spherical(b)) / (ca + cb))
            cout = ca + cb
        else:
            if cb > ca:
                out = b
                cout = cb
        for k in ti.static(range(3)):
            Xo[n, k] = out[k]
        Co[n] = cout


def update_pointmap(
    state: PointmapState,
    X: Any,
    C: Any,
    cfg: FusionConfig = FusionConfig(),  # noqa: B008 (frozen, immutable)
) -> PointmapState:
    """Taichi twin of ``mslam_ref.fusion.update_pointmap``."""
    mode = cfg.filtering_mode
    if state.N == 0 or mode not in _KERNEL_MODES:
        return ref_fusion.update_pointmap(state, X, C, cfg)
    X, C = ref_fusion.check_pointmap(X, C)
    if X.shape != state.X_canon.shape:
        raise ValueError(f"X: expected shape {state.X_canon.shape}, got {X.shape}")
    dtype = ensure_init().dtype
    c = lambda a, s: np.ascontiguousarray(np.reshape(a, s), dtype=dtype)
    n = C.size
    Xo, Co = np.empty((n, 3), dtype), np.empty(n, dtype)
    if n:
        _fuse_k(
            c(state.X_canon, (n, 3)),
            c(state.C, (n,)),
            c(X, (n, 3)),
            c(C, (n,)),
            Xo,
            Co,
            _KERNEL_MODES[mode],
        )
    N = 1 if mode == "indep_conf" else state.N + 1
    return PointmapState(
        Xo.reshape(X.shape), Co.reshape(C.shape), N, state.N_updates + 1, state.score
    )
