"""Bundle adjustment on Ladybug-49 (BAL): reference, fast, scipy least_squares and pyceres.

    python benchmarks/bench_ba.py [--repeat N] [--iterations 50] [--no-scipy] [--no-pyceres]
                                  [--arch cpu|cuda] [--data FILE]

Every solver gets the same iteration cap and the same stopping rule where it has one (Ceres'
``function_tolerance`` 1e-6). Times are best-of-N wall times of the solve only (file loading and
the Taichi compilation excluded by a warm-up). Writes the ``ba`` section of RESULTS.md
(``ba-cuda`` with ``--arch cuda``: the fast kernels on a GPU, the others as always).

* ref / fast: ``mslam_ref.ba.lm.optimize`` with ``LMConfig(jacobi_scaling=True,
  function_tolerance=1e-6)`` and the NumPy or Taichi kernel set.
* scipy: ``least_squares(method="trf", jac="2-point", jac_sparsity=..., x_scale="jac",
  max_nfev=cap)`` on the additive 9+3 parameterisation (the angle-axis vector itself).
* pyceres: Ceres through its Python bindings with one Python ``CostFunction`` per observation
  (analytic Jacobians; pyceres ships no compiled BAL factor), SPARSE_SCHUR, LM. Its time is
  dominated by ~32k Python callbacks per evaluation, so it is *not* native Ceres' speed; the
  native figure (0.7-1.1 s, 32 iterations, 13344.32) was measured separately on this machine.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: no spinning BLAS threads

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "reference"), str(ROOT / "fast"), str(ROOT / "benchmarks")]

from _data import BAL_LADYBUG_49, data_dir  # noqa: E402
from _results import table, write_section  # noqa: E402

from mslam import bal as io  # noqa: E402
from mslam_ref.ba import cameras, lm, synthetic  # noqa: E402

CERES_NATIVE = "0.7-1.1 s, 32 it., 13344.32 (native Ceres SPARSE_SCHUR, measured separately)"


def _timed(fn, repeat: int):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run_mslam(problem, kernels, cap: int, repeat: int):
    cfg = lm.LMConfig(iterations=cap, jacobi_scaling=True, function_tolerance=1e-6)
    tiny, _ = synthetic.make_bal_problem(n_cams=3, n_points=10)
    lm.optimize(tiny, lm.LMConfig(iterations=1), kernels)  # warm-up / compile
    t, res = _timed(lambda: lm.optimize(problem, cfg, kernels), repeat)
    return t, res.final_cost, res.iterations, res.profile


def run_scipy(problem, cap: int):
    import scipy.sparse
    from scipy.optimize import least_squares

    M, P, O = len(problem.cameras), len(problem.points), len(problem.obs)

    def fun(x):
        return cameras.bal_residuals(x[: 9 * M].reshape(M, 9), x[9 * M :].reshape(P, 3),
                                     problem.obs_cam, problem.obs_pt, problem.obs).ravel()  # fmt: skip

    rows = np.repeat(np.arange(2 * O), 12)
    cols = np.concatenate([
        np.concatenate([problem.obs_cam[:, None] * 9 + np.arange(9), 9 * M + problem.obs_pt[:, None] * 3 + np.arange(3)], 1)
    ] * 1)  # fmt: skip
    cols = np.repeat(cols, 2, axis=0).ravel()
    A = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * O, 9 * M + 3 * P))
    x0 = np.r_[problem.cameras.ravel(), problem.points.ravel()]
    t0 = time.perf_counter()
    res = least_squares(fun, x0, jac="2-point", jac_sparsity=A, method="trf", x_scale="jac",
                        max_nfev=cap, ftol=1e-6)  # fmt: skip
    return time.perf_counter() - t0, float(res.cost), int(res.nfev)


def run_pyceres(problem, cap: int):
    import pyceres

    class BALCost(pyceres.CostFunction):
        def __init__(self, obs):
            super().__init__()
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([9, 3])
            self.obs = obs

        def Evaluate(self, params, residuals, jacobians):
            c, X = params[0], params[1]
            r, Jc, Jp = _bal_additive(np.asarray(c), np.asarray(X), self.obs)
            residuals[0], residuals[1] = r
            if jacobians is not None:
                if jacobians[0] is not None:
                    jacobians[0][:] = Jc.ravel()
                if jacobians[1] is not None:
                    jacobians[1][:] = Jp.ravel()
            return True

    cams = problem.cameras.copy()
    pts = problem.points.copy()
    prob = pyceres.Problem()
    costs = []
    for e in range(len(problem.obs)):
        cost = BALCost(problem.obs[e].copy())
        costs.append(cost)
        prob.add_residual_block(cost, None, [cams[problem.obs_cam[e]], pts[problem.obs_pt[e]]])
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    opts.max_num_iterations = cap
    opts.function_tolerance = 1e-6
    opts.num_threads = 2
    opts.minimizer_progress_to_stdout = False
    summary = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(opts, prob, summary)
    return (
        time.perf_counter() - t0,
        float(summary.final_cost),
        int(summary.num_successful_steps + summary.num_unsuccessful_steps),
    )


def _bal_additive(c, X, obs):
    """Residual and Jacobians of one observation w.r.t. the additive angle-axis parameters."""
    w = c[:3]
    th = np.linalg.norm(w)
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-8:
        R, Jr = np.eye(3) + W, np.eye(3) - 0.5 * W
    else:
        R = np.eye(3) + np.sin(th) / th * W + (1 - np.cos(th)) / th**2 * W @ W
        Jr = np.eye(3) - (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W @ W
    P = R @ X + c[3:6]
    p = -P[:2] / P[2]
    r2 = p @ p
    d = 1 + c[7] * r2 + c[8] * r2 * r2
    f = c[6]
    r = f * d * p - obs
    Dp = f * d * np.eye(2) + 2 * f * (c[7] + 2 * c[8] * r2) * np.outer(p, p)
    iz = 1 / P[2]
    A = Dp @ np.array([[-iz, 0, P[0] * iz * iz], [0, -iz, P[1] * iz * iz]])
    Xh = np.array([[0, -X[2], X[1]], [X[2], 0, -X[0]], [-X[1], X[0], 0]])
    Jc = np.concatenate([A @ (-R @ Xh @ Jr), A, (d * p)[:, None], (f * r2 * p)[:, None],
                         (f * r2 * r2 * p)[:, None]], 1)  # fmt: skip
    return r, Jc, A @ R


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--no-scipy", action="store_true")
    ap.add_argument("--no-pyceres", action="store_true")
    ap.add_argument("--arch", choices=["cpu", "cuda"], default="cpu", help="Taichi backend")
    ap.add_argument(
        "--data",
        default=str(data_dir() / BAL_LADYBUG_49),
        help="the BAL file (default: Ladybug-49 in $MSLAM_DATA, else the shared data folder)",
    )
    args = ap.parse_args()
    problem = io.read_bal(args.data)
    import mslam_fast
    from mslam.kernels import load_kernels

    mslam_fast.init(args.arch, "f64")

    fast_ba, ref_ba = load_kernels("fast").ba, load_kernels("ref").ba

    rows = []
    load0 = os.getloadavg()[0]
    t, cost, it, prof = run_mslam(problem, fast_ba, args.iterations, args.repeat)
    rows.append(
        [
            f"mslam fast (Taichi {args.arch.upper()})",
            f"{t:.3f}",
            f"{cost:.2f}",
            it,
            f"best of {args.repeat}",
        ]
    )
    fast_prof = prof
    t, cost, it, _ = run_mslam(problem, ref_ba, args.iterations, max(1, args.repeat // 2))
    rows.append(
        [
            "mslam reference (NumPy)",
            f"{t:.3f}",
            f"{cost:.2f}",
            it,
            f"best of {max(1, args.repeat // 2)}",
        ]
    )
    if not args.no_scipy:
        t, cost, nfev = run_scipy(problem, args.iterations)
        rows.append(["scipy least_squares trf", f"{t:.3f}", f"{cost:.2f}", f"{nfev} nfev", "1 run"])
    if not args.no_pyceres:
        try:
            t, cost, it = run_pyceres(problem, args.iterations)
            rows.append(["pyceres (Python cost functions)", f"{t:.3f}", f"{cost:.2f}", it, "1 run"])
        except ImportError:
            rows.append(["pyceres", "n/a", "n/a", "-", "not importable"])
    rows.append(["native Ceres (reference figure)", "0.7-1.1", "13344.32", 32, "not run here"])
    load1 = os.getloadavg()[0]
    body = table(["solver", "solve s", "final cost", "iterations", "timing"], rows)
    prof_rows = [[k, f"{1e3 * v:.1f}"] for k, v in fast_prof.items()]
    body += (
        "\n\nLadybug-49 (49 cameras, 7776 points, 31843 observations), initial cost 8.509125e+05, "
        f"iteration cap {args.iterations}, function tolerance 1e-6. "
        f"Load average {load0:.1f} -> {load1:.1f} during the run (other jobs share the 2 cores; "
        "best-of-N reduces but does not remove that noise).\n\n"
        "Fast per-stage profile (ms, last run):\n\n" + table(["stage", "ms"], prof_rows)
    )
    print(body)
    if args.arch == "cpu":
        write_section("ba", "Bundle adjustment (Ladybug-49)", body)
    else:
        write_section("ba-cuda", "Bundle adjustment (Ladybug-49), fast kernels on CUDA", body)


if __name__ == "__main__":
    main()
