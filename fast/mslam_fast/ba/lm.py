"""Taichi twin of ``mslam_ref.ba.lm`` — the *same* LM driver, run with the fast kernel set.

Nothing is re-implemented here: ``optimize``, ``robust_chi2`` and ``solve_damped`` call the
reference driver with ``kernels=mslam_fast.ba`` when ``kernels`` is None, so the schedule,
stopping rules and profile are identical and only the kernels (``cameras``, ``schur``) differ.
"""

from __future__ import annotations

from typing import Any

from mslam_ref.ba import lm as _ref
from mslam_ref.ba.lm import PROFILE_KEYS, LMConfig, LMResult

__all__ = ["PROFILE_KEYS", "LMConfig", "LMResult", "optimize", "robust_chi2", "solve_damped"]


def _fast() -> Any:
    import mslam_fast.ba as fast_ba

    return fast_ba


def robust_chi2(problem: Any, kernels: Any, cams: Any, points: Any) -> float:
    """Taichi twin of ``mslam_ref.ba.lm.robust_chi2`` (``kernels`` as given)."""
    return _ref.robust_chi2(problem, kernels, cams, points)


def solve_damped(blocks: tuple[Any, ...], lam: float, structure: Any, kernels: Any = None) -> Any:
    """Taichi twin of ``mslam_ref.ba.lm.solve_damped`` (default kernel set: ``mslam_fast.ba``)."""
    return _ref.solve_damped(blocks, lam, structure, kernels if kernels is not None else _fast())


def optimize(problem: Any, config: LMConfig | None = None, kernels: Any = None) -> LMResult:
    """Taichi twin of ``mslam_ref.ba.lm.optimize`` (default kernel set: ``mslam_fast.ba``)."""
    return _ref.optimize(problem, config, kernels if kernels is not None else _fast())
