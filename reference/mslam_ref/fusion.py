"""Paper §3.3 — Pointmap fusion: a keyframe's canonical pointmap as a running average.

Every time a frame f is tracked against a keyframe k, the network's prediction of the
keyframe's own pointmap in that pair, ``X^k_f`` (image k in camera f, pixel-aligned with k),
is moved into camera k with the estimated pose and fused, with its confidence ``C^k_f``, into
the keyframe's *canonical* pointmap: the fused quantity is ``T_kf · X^k_f`` (upstream
``Xkf``, ``Ckf``), not the frame's own ``X^f_f``. The default is a confidence-weighted running average
(paper Eq. 8); upstream ships five alternatives for the ablation of Table 5. Downstream code
(matching masks, tracking, the backend) uses the *average* confidence ``C / N``.

The state is an immutable :class:`PointmapState`; :func:`update_pointmap` returns a new one.

Public names, in reading order:
    FILTERING_MODES, FusionConfig, PointmapState, init_pointmap, update_pointmap,
    average_confidence, to_spherical, from_spherical
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mslam_ref.conventions import FloatArray, as_float_array

__all__ = [
    "FILTERING_MODES",
    "FusionConfig",
    "PointmapState",
    "average_confidence",
    "check_pointmap",
    "from_spherical",
    "init_pointmap",
    "to_spherical",
    "update_pointmap",
]

#: Upstream's ``tracking.filtering_mode`` values (frame.py::Frame.update_pointmap).
FILTERING_MODES = (
    "weighted_pointmap",
    "weighted_spherical",
    "recent",
    "first",
    "best_score",
    "indep_conf",
)


@dataclasses.dataclass(frozen=True)
class FusionConfig:
    """Upstream's ``tracking.filtering_mode`` and ``tracking.filtering_score`` (median|mean)."""

    filtering_mode: str = "weighted_pointmap"
    filtering_score: str = "median"

    def __post_init__(self) -> None:
        if self.filtering_mode not in FILTERING_MODES:
            raise ValueError(
                f"filtering_mode: expected one of {FILTERING_MODES}, got {self.filtering_mode!r}"
            )
        if self.filtering_score not in ("median", "mean"):
            raise ValueError(
                f"filtering_score: expected 'median' or 'mean', got {self.filtering_score!r}"
            )


@dataclasses.dataclass(frozen=True, eq=False)
class PointmapState:
    """A keyframe's canonical pointmap.

    Attributes:
        X_canon: (N, 3) fused points in the keyframe's camera (any leading shape is kept).
        C: (N,) accumulated confidence (a sum for the weighted modes).
        N: number of predictions averaged into ``X_canon`` (1 after a replacement).
        N_updates: number of calls so far, including the initialisation.
        score: median (or mean) of the confidence that set the pointmap (``best_score`` only;
            computed for every mode, harmless).
    """

    X_canon: FloatArray
    C: FloatArray
    N: int
    N_updates: int
    score: float


def _score(C: FloatArray, cfg: FusionConfig) -> float:
    if C.size == 0:
        return 0.0
    return float(np.median(C) if cfg.filtering_score == "median" else np.mean(C))


def check_pointmap(X: Any, C: Any) -> tuple[FloatArray, FloatArray]:
    """Validate a pointmap ``X`` (..., 3) and its confidences ``C`` (...), C > 0; float64."""
    X = as_float_array(X, "X", 3)
    C = as_float_array(C, "C")
    if C.shape != X.shape[:-1]:
        raise ValueError(f"C: expected shape {X.shape[:-1]} to match X, got {C.shape}")
    if np.any(C <= 0.0):
        raise ValueError("C: confidences must be positive (MASt3R's are >= 1)")
    return X, C


def init_pointmap(
    X: FloatArray,
    C: FloatArray,
    cfg: FusionConfig = FusionConfig(),
) -> PointmapState:
    """State after the first prediction: ``X_canon = X, C = C, N = 1, N_updates = 1``.

    Upstream: frame.py::Frame.update_pointmap (the ``N == 0`` branch).

    Args:
        X: (N, 3) points; C: (N,) confidences > 0.
        cfg: fusion configuration (the score statistic).

    Returns:
        a new :class:`PointmapState` (copies of X and C).
    """
    X, C = check_pointmap(X, C)
    return PointmapState(X.copy(), C.copy(), 1, 1, _score(C, cfg))


def to_spherical(X: FloatArray) -> FloatArray:
    """``(r, phi, theta) = (|X|, atan2(y, x), acos(z/r))``; the origin maps to (0, 0, 0)."""
    r = np.linalg.norm(X, axis=-1)
    cos_t = np.clip(X[..., 2] / np.where(r > 0.0, r, 1.0), -1.0, 1.0)
    return np.stack([r, np.arctan2(X[..., 1], X[..., 0]), np.arccos(cos_t)], -1)


def from_spherical(S: FloatArray) -> FloatArray:
    """Inverse of :func:`to_spherical`."""
    r, phi, th = S[..., 0], S[..., 1], S[..., 2]
    st = np.sin(th)
    return np.stack([r * st * np.cos(phi), r * st * np.sin(phi), r * np.cos(th)], -1)


def update_pointmap(
    state: PointmapState,
    X: FloatArray,
    C: FloatArray,
    cfg: FusionConfig = FusionConfig(),
) -> PointmapState:
    """Fuse a new prediction ``(X', C')`` into the canonical pointmap.

    Paper: §3.3, Eq. (8) (``weighted_pointmap``); Table 5 (the others).
    Upstream: frame.py::Frame.update_pointmap. Per pixel:

        weighted_pointmap   X <- (C X + C' X') / (C + C'),  C <- C + C',  N += 1
        weighted_spherical  the same average of (r, phi, theta), back to Cartesian (no
                            angle-wrap handling, as upstream),        C <- C + C',  N += 1
        recent              X <- X', C <- C', N = 1
        first               replace (N = 1) only when N_updates == 1, then never again
        best_score          replace (N = 1) when score(C') > stored score; score updated
        indep_conf          where C' > C: X <- X', C <- C';  N = 1
        and always          N_updates += 1

    A state with ``N == 0`` is initialised as :func:`init_pointmap`.

    Args:
        state: the current state.
        X: new points, same shape as ``state.X_canon``; C: new confidences (> 0).
        cfg: ``filtering_mode`` and ``filtering_score``.

    Returns:
        a new :class:`PointmapState` (the input state is not modified).
    """
    X, C = check_pointmap(X, C)
    if state.N == 0:
        return init_pointmap(X, C, cfg)
    if X.shape != state.X_canon.shape:
        raise ValueError(f"X: expected shape {state.X_canon.shape}, got {X.shape}")
    Xs, Cs, N, score = state.X_canon, state.C, state.N, state.score
    mode = cfg.filtering_mode
    if mode == "weighted_pointmap":
        Xs = (Cs[..., None] * Xs + C[..., None] * X) / (Cs + C)[..., None]
        Cs, N = Cs + C, N + 1
    elif mode == "weighted_spherical":
        S = (Cs[..., None] * to_spherical(Xs) + C[..., None] * to_spherical(X)) / (Cs + C)[
            ..., None
        ]
        Xs, Cs, N = from_spherical(S), Cs + C, N + 1
    elif mode == "recent":
        Xs, Cs, N = X.copy(), C.copy(), 1
    elif mode == "first":
        if state.N_updates == 1:
            Xs, Cs, N = X.copy(), C.copy(), 1
    elif mode == "best_score":
        new_score = _score(C, cfg)
        if new_score > score:
            Xs, Cs, N, score = X.copy(), C.copy(), 1, new_score
    else:  # indep_conf
        better = C > Cs
        Xs = np.where(better[..., None], X, Xs)
        Cs, N = np.where(better, C, Cs), 1
    return PointmapState(Xs, Cs, N, state.N_updates + 1, score)


def average_confidence(state: PointmapState) -> FloatArray:
    """The confidence used downstream, ``C / N`` (the mean for the weighted modes).

    Returns:
        (N,) float64.
    """
    return state.C / float(state.N)
