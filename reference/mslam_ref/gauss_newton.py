"""Paper §3.3 and §3.5 — the one iteratively re-weighted Gauss–Newton driver.

Tracking (one relative Sim(3), paper §3.3) and the backend (all keyframe poses, paper §3.5)
minimise robust least-squares costs the same way: at the current estimate ``x``, linearise
(residuals, Jacobians and Huber weights give the normal equations ``H dx = -g``), solve for a
step, apply it on the manifold by left retraction, and repeat until a stopping test holds.
What differs is only the problem: how a step is computed (a dense 7x7 Cholesky, or a sparse
system over many poses), what a failed solve means, and when to stop. This module holds the
loop; the two callers pass those three pieces in.

    x = x0
    repeat up to max_iters:
        dx, cost = step(x)             (cost at x, before the update)
        if dx is None (the solve failed):
            abort: return x0           (tracking: the caller relocalises)
            or take zero_step          (backend: as upstream, the iteration is wasted)
        x = retract(x, dx)
        stop if converged(old_cost, cost, dx)
        old_cost = cost

Public names, in reading order: GNTrace, gauss_newton, cholesky_step, small_change.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from mslam_ref.conventions import FloatArray

__all__ = ["GNTrace", "cholesky_step", "gauss_newton", "small_change"]


@dataclasses.dataclass(frozen=True)
class GNTrace:
    """What one run of :func:`gauss_newton` did.

    Attributes:
        costs: the cost at the estimate of every iteration, before its update.
        step_norms: ``|dx|`` of every step taken (a zero step counts).
        failed: iterations whose solve failed.
        converged: the stopping test held.
        aborted: a failed solve ended the run and the initial estimate was returned.
    """

    costs: tuple[float, ...]
    step_norms: tuple[float, ...]
    failed: int
    converged: bool
    aborted: bool

    @property
    def iterations(self) -> int:
        """Number of linearisations (iterations) run."""
        return len(self.costs)


StepFn = Callable[[Any], tuple[FloatArray | None, float]]
RetractFn = Callable[[Any, FloatArray], Any]
StopFn = Callable[[float, float, FloatArray], bool]


def gauss_newton(
    x0: Any,
    step: StepFn,
    retract: RetractFn,
    converged: StopFn,
    max_iters: int,
    zero_step: FloatArray | None = None,
) -> tuple[Any, GNTrace]:
    """Run the IRLS Gauss–Newton loop of the module docstring.

    Args:
        x0: the initial estimate (any value ``retract`` accepts; not modified).
        step: ``step(x) -> (dx, cost)``: the Gauss–Newton step at ``x`` (None when the
            solve failed) and the robust cost at ``x``.
        retract: ``retract(x, dx) -> x'`` (left retraction on the manifold).
        converged: ``converged(old_cost, cost, dx) -> bool``; ``old_cost`` is ``inf`` at the
            first iteration.
        max_iters: at most this many iterations (0 returns ``x0``).
        zero_step: on a failed solve, take this step and go on; None aborts instead.

    Returns:
        x: the estimate (``x0`` when aborted); trace: a :class:`GNTrace`.
    """
    x, old_cost = x0, math.inf
    costs: list[float] = []
    norms: list[float] = []
    failed = 0
    for _ in range(int(max_iters)):
        dx, cost = step(x)
        costs.append(float(cost))
        if dx is None:
            failed += 1
            if zero_step is None:
                return x0, GNTrace(tuple(costs), tuple(norms), failed, False, True)
            dx = zero_step
        x = retract(x, dx)
        norms.append(float(np.linalg.norm(dx)))
        if converged(old_cost, float(cost), dx):
            return x, GNTrace(tuple(costs), tuple(norms), failed, True, False)
        old_cost = float(cost)
    return x, GNTrace(tuple(costs), tuple(norms), failed, False, False)


def cholesky_step(H: Any, g: Any) -> FloatArray | None:
    """The dense Gauss–Newton step ``H^-1 g`` by Cholesky (the sign is the caller's: tracking
    passes ``g = -A^T b``).

    Returns:
        the step, or None when H is not positive definite or the step is not finite.
    """
    try:
        L = np.linalg.cholesky(np.asarray(H, dtype=np.float64))
        tau = np.linalg.solve(L.T, np.linalg.solve(L, np.asarray(g, dtype=np.float64)))
    except np.linalg.LinAlgError:
        return None
    return tau if np.all(np.isfinite(tau)) else None


def small_change(rel_error: float, delta_norm: float) -> StopFn:
    """Upstream tracking's stopping rule, as a ``converged`` argument of :func:`gauss_newton`:
    stop when ``|(old_cost - cost) / old_cost| < rel_error`` or ``|dx| < delta_norm``.

    The costs are the *pre-update* ones; at the first step (``old_cost = inf``) only ``|dx|``
    can stop. Where upstream would divide 0 by 0 (two zero costs) it reports convergence.
    """

    def converged(old_cost: float, cost: float, dx: FloatArray) -> bool:
        if math.isinf(old_cost):
            rel = math.nan
        elif old_cost == 0.0:
            rel = 0.0
        else:
            rel = abs((old_cost - cost) / old_cost)
        return rel < rel_error or float(np.linalg.norm(dx)) < delta_norm

    return converged
