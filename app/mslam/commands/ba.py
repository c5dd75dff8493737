"""``mslam ba PROBLEM``: bundle-adjust a BAL or g2o problem file and print the result as JSON.

    mslam ba problem-49-7776-pre.txt [--kernels ref|fast] [--iterations N] [--out FILE.bal]
                                     [--damping jacobi|identity] [--function-tolerance T]
    mslam ba graph.g2o [--robust none|huber|tukey] ...   (SE(3) + XYZ, ``mslam.g2o_ba``)

The JSON holds ``initial_cost``, ``final_cost`` (0.5 sum of squared residuals, as Ceres),
``iterations``, ``stop_reason``, ``seconds`` (the solve only: file loading and, with
``--kernels fast``, the first Taichi compilation are excluded by a warm-up solve on a tiny
synthetic problem) and the per-stage ``profile`` (cuda-bundle-adjustment's eight items).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path
from typing import Any

# Small dense Cholesky factorisations are fastest on one BLAS thread; several BLAS threads spin
# and steal the cores from the Taichi kernels (only effective when numpy is not yet imported).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from mslam.commands import UserError, print_json

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``ba`` sub-parser."""
    p = subparsers.add_parser(
        "ba",
        help="bundle-adjust a BAL problem (LM + Schur complement)",
        description="Levenberg-Marquardt bundle adjustment (g2o schedule, Schur complement) of "
        "a BAL problem file; prints JSON.",
    )
    p.add_argument("problem", type=Path, help="BAL problem file (problem-*.txt) or g2o file (.g2o)")
    p.add_argument("--robust", choices=("none", "huber", "tukey"), default="none",
                   help="robust kernel of a .g2o problem (deltas sqrt(5.991) mono, sqrt(7.815) "
                   "stereo; default none)")  # fmt: skip
    p.add_argument("--kernels", choices=("ref", "fast"), default="ref")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="where the fast kernels run; cuda needs an NVIDIA GPU (default: cpu)")  # fmt: skip
    p.add_argument("--iterations", type=int, default=50, help="LM iteration cap (default 50)")
    p.add_argument("--out", type=Path, default=None, help="write the optimised problem (BAL file)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--damping", choices=("jacobi", "identity"), default="jacobi",
                   help="jacobi: Ceres' Jacobi scaling (default); identity: g2o's lambda I")  # fmt: skip
    p.add_argument("--function-tolerance", type=float, default=1e-6,
                   help="stop when the relative cost decrease is below this (0 = off)")  # fmt: skip
    p.set_defaults(func=run)


def _kernel_set(name: str, cfg: Any) -> Any:
    """The BA kernels of the kernel set ``name``; the fast kernels are compiled on a tiny
    problem first, with the run's settings (Jacobi scaling or not), so the timed solve
    measures the solve, not Taichi's compilation."""
    from mslam.kernels import load_kernels
    from mslam_ref.ba import lm, synthetic

    kernels = load_kernels(name).ba
    if name == "fast":
        tiny, _ = synthetic.make_bal_problem(n_cams=3, n_points=10)
        lm.optimize(tiny, dataclasses.replace(cfg, iterations=2), kernels)
    return kernels


def _load(args: argparse.Namespace) -> tuple[Any, Any]:
    """The problem and the function that formats its optimised copy for ``--out``."""
    if args.problem.suffix == ".g2o":
        from mslam.g2o_ba import format_g2o_ba, read_g2o_ba

        problem, ids = read_g2o_ba(args.problem, robust=args.robust)
        return problem, lambda q: format_g2o_ba(q, ids)
    from mslam import bal as io

    return io.read_bal(args.problem), io.format_bal


def run(args: argparse.Namespace) -> int:
    """Load, solve, report (and optionally write)."""
    from mslam.device import use_device
    from mslam_ref.ba import lm

    if args.iterations < 0:
        raise UserError(f"--iterations must be >= 0, got {args.iterations}")
    use_device(args.device, args.kernels)
    if not args.problem.is_file():
        raise FileNotFoundError(f"{args.problem}: no such file")
    if args.out is not None:
        from mslam.outdir import check_target

        check_target(args.out, args.overwrite, kind="file")
    problem, fmt = _load(args)
    cfg = lm.LMConfig(
        iterations=args.iterations,
        jacobi_scaling=args.damping == "jacobi",
        function_tolerance=max(0.0, args.function_tolerance),
    )
    kernels = _kernel_set(args.kernels, cfg)
    t0 = time.perf_counter()
    res = lm.optimize(problem, cfg, kernels)
    seconds = time.perf_counter() - t0
    if args.out is not None:
        from mslam.outdir import write_file_atomic

        write_file_atomic(args.out, fmt(res.problem), args.overwrite)
    print_json(
        {
            "problem": str(args.problem),
            "cameras": len(problem.params()[0]),
            "points": len(problem.points),
            "observations": len(problem.obs_cam),
            "kernels": args.kernels,
            "device": args.device,
            "initial_cost": res.initial_cost,
            "final_cost": res.final_cost,
            "iterations": res.iterations,
            "stop_reason": res.stop_reason,
            "seconds": seconds,
            "profile": res.profile,
            "history": [h["cost"] for h in res.history],
        }
    )
    return 0
