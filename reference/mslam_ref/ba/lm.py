r"""Bundle adjustment — the Levenberg–Marquardt driver of g2o (``OptimizationAlgorithmLevenberg``).

Cost. With per-edge squared errors ``s_e = omega_e |r_e|^2`` the robust chi2 is
``F = sum_e rho(s_e)``; the reported cost is ``F / 2`` (Ceres' ``0.5 sum |r|^2`` without a
robust kernel).

One iteration (g2o's schedule, as cuda-bundle-adjustment copies it):

    linearise at x: r, J, w = omega rho'(s), F = sum rho(s)            schur.normal_blocks
    k = 0:  lam = tau * max diag(H)          (tau = 1e-5, over U and V)
    repeat up to max_trials = 10 times while rho <= 0:
        solve  [U + lam I, W; W^T, V + lam I] [dc; dl] = [bc; bl]         solve_damped
        x_new = x (+) [dc; dl]                                          problem.retract
        F_new = sum rho(s(x_new))
        scale = dx^T (lam dx + b) + 1e-3              (predicted decrease of F)
        rho   = (F - F_new) / scale                   (-1 when the Cholesky fails)
        rho > 0:  lam *= clamp(1 - (2 rho - 1)^3, 1/3, 2/3),  nu = 2,  accept
        else:     lam *= nu,  nu *= 2,  restore x
    stop when every trial failed, lam is not finite, or (optional, Ceres' rule)
    (F - F_new) <= function_tolerance * F.

Two documented additions to g2o: a trial is accepted only when ``F_new < F`` as well as
``rho > 0`` (so round-off in a near-singular ``scale`` can never raise the cost), and the optional
Jacobi scaling of Ceres (``LMConfig.jacobi_scaling``; the blocks then come from
``schur.scaled_normal_blocks``, which a kernel set may compute without the unscaled W).

``dx^T (lam dx + b)`` is the decrease of the Gauss-Newton model ``F - m(dx)`` at the damped step:
with ``(H + lam I) dx = b``, ``2 dx^T b - dx^T H dx = dx^T (lam dx + b)``.

The driver is shared by both kernel sets: ``kernels`` is any object with ``cameras`` and
``schur`` modules — those of ``mslam_ref.ba`` (the default) or their Taichi twins in
``mslam_fast.ba`` (the application's kernel set passes one). The reduced camera system is
analysed once per call (``reduced.analyse``: ordering and storage, the "symbolic_decomposition"
stage) and refactored every trial (``reduced.factor_solve``, "numerical_decomposition"), by the
kernel set's ``reduced`` functions where it has them, else ``mslam_ref.ba.reduced``'s.

Public names, in reading order: LMConfig, LMResult, PROFILE_KEYS, robust_chi2, solve_damped,
optimize.

Upstream: g2o core/optimization_algorithm_levenberg.cpp (solve, computeLambdaInit, computeScale);
cuda-bundle-adjustment src/cuda_bundle_adjustment.cpp (CudaBundleAdjustmentImpl::optimize,
timeProfile, batchStatistics).
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import numpy as np

from mslam_ref.ba import reduced as _reduced
from mslam_ref.ba import schur as _schur
from mslam_ref.ba.profile import StageClock
from mslam_ref.conventions import FloatArray

__all__ = ["PROFILE_KEYS", "LMConfig", "LMResult", "optimize", "robust_chi2", "solve_damped"]

#: The time-profile items of cuda-bundle-adjustment's ``timeProfile()`` (seconds).
PROFILE_KEYS = (
    "initialize",
    "build_structure",
    "compute_error",
    "build_system",
    "schur_complement",
    "symbolic_decomposition",
    "numerical_decomposition",
    "update_solution",
)


@dataclasses.dataclass(frozen=True)
class LMConfig:
    """LM settings; names and defaults follow g2o ``OptimizationAlgorithmLevenberg``.

    Attributes:
        iterations: maximum LM iterations (each with up to ``max_trials`` solves).
        tau: initial damping factor, ``lam0 = tau * max diag(H)`` (g2o ``_tau``).
        max_trials: trials per iteration (g2o ``_maxTrialsAfterFailure``).
        good_step_lower, good_step_upper: clamp of the lambda shrink factor (1/3, 2/3).
        function_tolerance: extra stop (Ceres): stop when the accepted decrease is at most this
            fraction of F. 0 (default) reproduces g2o's loop exactly.
        jacobi_scaling: solve in the variables scaled by ``D = 1 / (1 + sqrt(diag H))`` (Ceres'
            ``jacobi_scaling``), which turns ``lam I`` into Marquardt's ``lam D^-2`` damping and
            makes the schedule independent of the parameter units. Off (default) is g2o; on is
            much faster on BAL problems, whose focal lengths and distortions differ by 1e9
            in scale.
    """

    iterations: int = 50
    tau: float = 1e-5
    max_trials: int = 10
    good_step_lower: float = 1.0 / 3.0
    good_step_upper: float = 2.0 / 3.0
    function_tolerance: float = 0.0
    jacobi_scaling: bool = False

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ValueError(f"iterations: must be >= 0, got {self.iterations}")
        if self.max_trials < 1:
            raise ValueError(f"max_trials: must be >= 1, got {self.max_trials}")
        if not self.tau > 0.0:
            raise ValueError(f"tau: must be positive, got {self.tau}")


@dataclasses.dataclass(frozen=True, eq=False)
class LMResult:
    """Outcome of :func:`optimize`.

    Attributes:
        problem: the problem with the optimised parameters.
        initial_cost, final_cost: ``F / 2`` before and after.
        iterations: LM iterations run.
        history: per iteration ``{"iteration", "cost", "lambda", "trials", "accepted", "gain"}``
            (``lambda`` after the iteration's update; ``gain`` the gain ratio of its last trial).
        profile: seconds per stage, keys ``PROFILE_KEYS``.
        edge_chi2: (O,) ``omega |r|^2`` per edge at the end, without the kernel (0 for dropped
            edges), as cuda-bundle-adjustment's ``chiSquared(e)``.
        stop_reason: "iterations", "no_decrease", "function_tolerance" or "lambda".
    """

    problem: Any
    initial_cost: float
    final_cost: float
    iterations: int
    history: tuple[dict[str, Any], ...]
    profile: dict[str, float]
    edge_chi2: FloatArray
    stop_reason: str


def _default_kernels() -> Any:
    """The reference kernels (``cameras`` and ``schur`` of ``mslam_ref.ba``)."""
    from mslam_ref.ba import cameras

    return SimpleNamespace(cameras=cameras, schur=_schur)


def robust_chi2(problem: Any, kernels: Any, cams: FloatArray, points: FloatArray) -> float:
    """Robust chi2 ``F = sum rho(omega |r|^2)`` over active edges at ``(cams, points)``."""
    r = problem.residuals(kernels, cams, points)
    s = problem.information * np.sum(r * r, axis=-1)
    return float(np.sum(problem.robust(s)[0]))


def _check_finite_start(problem: Any, kernels: Any, cams: FloatArray, points: FloatArray) -> None:
    """``ValueError`` naming the first observation whose residual is not finite at the start
    (a point at a camera centre, depth 0). Screened with the kernel set's residuals; when one is
    not finite, the message comes from the reference kernels' residuals, so both kernel sets give
    the same error before any of their steps runs."""
    with np.errstate(all="ignore"):
        if np.all(np.isfinite(problem.residuals(kernels, cams, points))):
            return
        r = problem.residuals(_default_kernels(), cams, points)
    bad = np.flatnonzero(~np.all(np.isfinite(r), axis=-1))
    if bad.size:
        o = int(bad[0])
        raise ValueError(
            f"observation {o} (camera {int(problem.obs_cam[o])}, point {int(problem.obs_pt[o])}): "
            f"residual is not finite at the start (the point lies at the camera centre, depth "
            f"0); {bad.size} such observation(s)"
        )


def solve_damped(
    blocks: tuple[FloatArray, ...], lam: float, structure: Any, kernels: Any = None
) -> tuple[FloatArray, FloatArray] | None:
    """One damped solve by Schur complement: ``(dc (M, d), dl (P, 3))`` or None on failure.

    Args:
        blocks: ``(U, V, W, bc, bl)`` from ``schur.normal_blocks``.
        lam: damping.
        structure: the ``BlockStructure``.
        kernels: kernel set (default ``mslam_ref.ba``).
    """
    k = kernels if kernels is not None else _default_kernels()
    U, V, W, bc, bl = blocks
    S, rhs, Vinv = k.schur.schur_complement(U, V, W, bc, bl, lam, structure)
    dc = _schur.solve_reduced(S, rhs, structure)
    if dc is None:
        return None
    return dc, k.schur.back_substitute(Vinv, W, bl, dc, structure)


def _linear_system(problem: Any, kernels: Any, structure: Any, cams, points, scaled: bool):
    """F and the blocks ``(U, V, W, bc, bl)`` at ``(cams, points)``; Jacobi-scaled, with the
    scales ``(Dc, Dp)``, when ``scaled`` (else None)."""
    r, Jc, Jp = problem.linearize(kernels, cams, points)
    s = problem.information * np.sum(r * r, axis=-1)
    rho, w = problem.robust(s)
    F, args = float(np.sum(rho)), (r, Jc, Jp, problem.information * w)
    if scaled:
        Us, Vs, Ws, bcs, bls, Dc, Dp = kernels.schur.scaled_normal_blocks(
            *args, problem.cam_free, problem.point_free, structure
        )
        return F, (Us, Vs, Ws, bcs, bls), (Dc, Dp)
    U, V, W, bc, bl = kernels.schur.normal_blocks(*args, structure)
    _schur.pin_fixed(U, V, bc, bl, problem.cam_free, problem.point_free)
    return F, (U, V, W, bc, bl), None


@dataclasses.dataclass
class _State:
    """The LM iterate: parameters, robust chi2 and the damping schedule."""

    cams: FloatArray
    points: FloatArray
    F: float
    lam: float = 0.0
    nu: float = 2.0


def _initial_lambda(problem: Any, blocks: tuple[FloatArray, ...], tau: float) -> float:
    """``lam0 = tau * max diag(H)`` over the free cameras and points (g2o computeLambdaInit)."""
    U, V = blocks[0], blocks[1]
    diag = np.concatenate(
        [np.diagonal(U[problem.cam_free], axis1=1, axis2=2).ravel(),
         np.diagonal(V[problem.point_free], axis1=1, axis2=2).ravel()]
    )  # fmt: skip
    return tau * float(diag.max()) if diag.size else tau


def _reduced_solver(kernels: Any) -> Any:
    """``analyse`` and ``factor_solve``: the kernel set's ``reduced`` functions where it has
    them, else the reference's."""
    mod = getattr(kernels, "reduced", None)
    return SimpleNamespace(
        analyse=getattr(mod, "analyse", _reduced.analyse),
        factor_solve=getattr(mod, "factor_solve", _reduced.factor_solve),
    )


def _trial(problem, k, st, state: _State, blocks, D, b, clock: StageClock) -> tuple[float, Any]:
    """One damped solve at ``state.lam``: the gain ratio rho (-1 on failure) and the new
    ``(cams, points, F)`` when the step was computed. ``st`` is ``(structure, symbolic)``."""
    U, V, W, bc, bl = blocks
    st, sym = st
    with clock("schur_complement"):
        S, rhs, Vinv = k.schur.schur_complement(U, V, W, bc, bl, state.lam, st)
    with clock("numerical_decomposition"):
        dc = _reduced_solver(k).factor_solve(sym, S, rhs)
    if dc is None:
        return -1.0, None
    with clock("schur_complement"):
        dl = k.schur.back_substitute(Vinv, W, bl, dc, st)
    dx = np.concatenate([dc.ravel(), dl.ravel()])  # the (scaled) step
    if D is not None:  # back to the unscaled variables for the update
        dc, dl = dc * D[0], dl * D[1]
    with clock("update_solution"):
        new_cams, new_points = problem.retract(state.cams, state.points, dc, dl)
    with clock("compute_error"):
        F_new = robust_chi2(problem, k, new_cams, new_points)
    scale = float(dx @ (state.lam * dx + b)) + 1e-3
    # g2o accepts rho > 0; F_new < F also guards a negative scale (round-off)
    ok = np.isfinite(F_new) and F_new < state.F
    return ((state.F - F_new) / scale if ok else -1.0), (new_cams, new_points, F_new)


def _damping_update(state: _State, rho: float, cfg: LMConfig) -> None:
    """g2o's schedule: shrink lam by ``clamp(1 - (2 rho - 1)^3, 1/3, 2/3)`` on success,
    otherwise multiply it by nu and double nu."""
    if rho > 0.0:
        alpha = 1.0 - (2.0 * rho - 1.0) ** 3
        state.lam *= max(cfg.good_step_lower, min(alpha, cfg.good_step_upper))
        state.nu = 2.0
    else:
        state.lam *= state.nu
        state.nu *= 2.0


def optimize(
    problem: Any,
    config: LMConfig | None = None,
    kernels: Any = None,
    clock: StageClock | None = None,
) -> LMResult:
    """Run g2o's Levenberg–Marquardt with Schur-complement solves.

    Args:
        problem: a ``BALProblem`` or ``PinholeProblem``.
        config: :class:`LMConfig` (default ``LMConfig()``).
        kernels: an object with ``cameras`` and ``schur`` modules (default: the reference's).
        clock: where the per-stage seconds are summed (default: a new
            ``mslam_ref.ba.profile.StageClock``); ``LMResult.profile`` reports it.

    Returns:
        An :class:`LMResult`; ``final_cost <= initial_cost`` always holds.

    Raises:
        ValueError: when a residual is not finite at the start (same message for both kernel
            sets); a step to a non-finite cost is rejected like any uphill step.
    """
    cfg = config if config is not None else LMConfig()
    k = kernels if kernels is not None else _default_kernels()
    clock = clock if clock is not None else StageClock(PROFILE_KEYS)
    with clock("initialize"):
        cams, points = problem.params()
        _check_finite_start(problem, k, cams, points)
    with clock("build_structure"):
        st = _schur.build_structure(
            problem.obs_cam, problem.obs_pt, len(cams), len(points), problem.cam_dof
        )
    with clock("symbolic_decomposition"):  # once: ordering, storage, scatter map
        sym = _reduced_solver(k).analyse(st)
    with clock("compute_error"):
        state = _State(cams, points, robust_chi2(problem, k, cams, points))
    F0, history, stop = state.F, [], "iterations"
    for it in range(cfg.iterations):
        blocks = D = None  # the previous system is released first: a kernel set may reuse it
        with clock("build_system"):
            state.F, blocks, D = _linear_system(
                problem, k, st, state.cams, state.points, cfg.jacobi_scaling
            )
        if it == 0:
            state.lam = _initial_lambda(problem, blocks, cfg.tau)
        b = np.concatenate([blocks[3].ravel(), blocks[4].ravel()])
        rho, trials, F_prev = -1.0, 0, state.F
        while rho <= 0.0 and trials < cfg.max_trials:
            trials += 1
            rho, new = _trial(problem, k, (st, sym), state, blocks, D, b, clock)
            if rho > 0.0:
                state.cams, state.points, state.F = new
            _damping_update(state, rho, cfg)
        history.append(
            {"iteration": it, "cost": 0.5 * state.F, "lambda": state.lam, "trials": trials,
             "accepted": rho > 0.0, "gain": rho}
        )  # fmt: skip
        stop = _stop_reason(rho, state, F_prev, cfg)
        if stop:
            break
    stop = stop or "iterations"
    with clock("compute_error"):
        r = problem.residuals(k, state.cams, state.points)
        chi2 = problem.information * np.sum(r * r, axis=-1)
    return LMResult(
        problem=problem.with_params(state.cams, state.points),
        initial_cost=0.5 * F0,
        final_cost=0.5 * state.F,
        iterations=len(history),
        history=tuple(history),
        profile=dict(clock.totals),
        edge_chi2=chi2,
        stop_reason=stop,
    )


def _stop_reason(rho: float, state: _State, F_prev: float, cfg: LMConfig) -> str:
    """Why the loop stops after this iteration ("" to go on)."""
    if rho <= 0.0:
        return "no_decrease"
    if not np.isfinite(state.lam):
        return "lambda"
    if cfg.function_tolerance > 0.0 and (F_prev - state.F) <= cfg.function_tolerance * F_prev:
        return "function_tolerance"
    return ""
