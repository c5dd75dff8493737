"""The native comparison solvers of bench_ba.py: Ceres (C++, built here) and g2o (g2opy).

* ``ceres``: ``benchmarks/native/ceres_bal.cc`` compiled once against the system's Ceres
  (Debian ``libceres-dev``, with SuiteSparse) into ``build/ceres_bal``; runs a BAL file in a
  subprocess and returns its JSON line (``time`` is Ceres' own solve time).
* ``g2o``: g2o (the ``g2opy`` wheel) ``SparseOptimizer`` with ``BlockSolverSE3`` (6x3 blocks, points marginalised),
  ``LinearSolverEigenSE3`` and ``OptimizationAlgorithmLevenberg`` — the configuration that
  cuda-bundle-adjustment replaces — on a ``PinholeProblem`` of monocular edges with one shared
  camera (``EdgeProjectXYZ2UV`` + ``CameraParameters``).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from mslam_ref import so3

ROOT = Path(__file__).resolve().parents[1]
CERES_SRC = ROOT / "benchmarks" / "native" / "ceres_bal.cc"
CERES_BIN = ROOT / "build" / "ceres_bal"


def ceres_binary() -> Path | None:
    """Build ``build/ceres_bal`` if needed; None when no compiler or Ceres is installed."""
    if CERES_BIN.exists() and CERES_BIN.stat().st_mtime >= CERES_SRC.stat().st_mtime:
        return CERES_BIN
    if shutil.which("g++") is None or not Path("/usr/include/ceres/ceres.h").exists():
        return None
    CERES_BIN.parent.mkdir(exist_ok=True)
    cmd = ["g++", "-O2", "-std=c++17", "-I/usr/include/eigen3", str(CERES_SRC), "-o",
           str(CERES_BIN), "-lceres", "-lglog", "-lgflags", "-lpthread"]  # fmt: skip
    return CERES_BIN if subprocess.run(cmd, check=False).returncode == 0 else None


def run_ceres(binary: Path, bal_file: Path, iterations: int, threads: int = 2) -> dict:
    """One native Ceres solve of a BAL file: ``{"time", "initial_cost", "final_cost", ...}``."""
    out = subprocess.run([str(binary), str(bal_file), str(iterations), str(threads)],
                         check=True, capture_output=True, text=True)  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def _g2o_graph(problem, work: Path):
    """The g2o graph of ``problem``, loaded by g2o's own reader from a file written into
    ``work`` by ``mslam.g2o_ba.format_g2o_ba`` (the seed's format), then the poses set through
    the bindings (world to camera: g2o versions read the file's pose in either direction) and
    the points marked for marginalisation. Built through the bindings vertex by vertex and
    edge by edge instead, a KITTI-00-sized graph does not finish: ``add_edge`` costs ~2 ms per
    call there, growing with the graph (2026-11-29: 100,000 edges in 438 s)."""
    import g2opy as g2o

    from mslam.g2o_ba import format_g2o_ba

    opt = g2o.SparseOptimizer()
    solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    algorithm = g2o.OptimizationAlgorithmLevenberg(solver)
    opt.set_algorithm(algorithm)
    M, P = len(problem.poses), len(problem.points)
    ids = {"poses": list(range(M)), "points": list(range(M, M + P))}
    path = work / "problem.g2o"
    path.write_text(format_g2o_ba(problem, ids).replace("VERTEX_SBAPOINTXYZ", "VERTEX_TRACKXYZ"))
    if (
        not opt.load(str(path))
        or len(opt.vertices()) != M + P
        or len(opt.edges()) != len(problem.obs_cam)
    ):
        raise RuntimeError(f"g2o did not load {path} whole")
    for i, T in enumerate(problem.poses):  # g2o's readers differ on the pose's direction
        R = np.asfortranarray(so3.to_matrix(np.asarray(T[3:], float)))
        opt.vertex(i).set_estimate(g2o.SE3Quat(R, np.asarray(T[:3], float)))
    for v in ids["points"]:
        opt.vertex(v).set_marginalized(True)
    return opt, [solver, algorithm]  # the bindings do not own these


def run_g2o(problem, iterations: int) -> dict:
    """g2o LM on a monocular ``PinholeProblem`` with one camera: time of ``optimize`` only,
    and the cost ``chi2 / 2`` before and after."""
    with tempfile.TemporaryDirectory() as work:
        opt, _alive = _g2o_graph(problem, Path(work))
    opt.initialize_optimization()
    opt.compute_active_errors()
    c0 = 0.5 * opt.active_chi2()
    t0 = time.perf_counter()
    opt.optimize(iterations)
    t = time.perf_counter() - t0
    opt.compute_active_errors()
    return {"time": t, "initial_cost": c0, "final_cost": 0.5 * opt.active_chi2()}
