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


def _g2o_graph(problem):
    import g2opy as g2o

    opt = g2o.SparseOptimizer()
    solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    algorithm = g2o.OptimizationAlgorithmLevenberg(solver)
    opt.set_algorithm(algorithm)
    fx, _fy, cx, cy, _ = problem.intrinsics[0]  # EdgeProjectXYZ2UV: one focal length
    cam = g2o.CameraParameters(float(fx), np.array([cx, cy], float), 0.0)
    cam.set_id(0)
    opt.add_parameter(cam)
    M, alive = len(problem.poses), [solver, algorithm, cam]  # the bindings do not own these
    for i, T in enumerate(problem.poses):
        v = g2o.VertexSE3Expmap()
        v.set_id(i)
        R = np.asfortranarray(so3.to_matrix(np.asarray(T[3:], float)))
        v.set_estimate(g2o.SE3Quat(R, np.asarray(T[:3], float)))
        v.set_fixed(bool(problem.pose_fixed[i]))
        opt.add_vertex(v)
        alive.append(v)
    for j, X in enumerate(problem.points):
        v = g2o.VertexPointXYZ()
        v.set_id(M + j)
        v.set_estimate(np.asarray(X, float))
        v.set_marginalized(True)
        opt.add_vertex(v)
        alive.append(v)
    for e in range(len(problem.obs_cam)):
        edge = g2o.EdgeProjectXYZ2UV()
        edge.set_vertex(0, opt.vertex(M + int(problem.obs_pt[e])))
        edge.set_vertex(1, opt.vertex(int(problem.obs_cam[e])))
        edge.set_measurement(np.asarray(problem.meas[e, :2], float))
        edge.set_information(np.eye(2) * float(problem.information[e]))
        edge.set_parameter_id(0, 0)
        opt.add_edge(edge)
        alive.append(edge)
    return opt, alive


def run_g2o(problem, iterations: int) -> dict:
    """g2o LM on a monocular ``PinholeProblem`` with one camera: time of ``optimize`` only,
    and the cost ``chi2 / 2`` before and after."""
    opt, _alive = _g2o_graph(problem)
    opt.initialize_optimization()
    opt.compute_active_errors()
    c0 = 0.5 * opt.active_chi2()
    t0 = time.perf_counter()
    opt.optimize(iterations)
    t = time.perf_counter() - t0
    opt.compute_active_errors()
    return {"time": t, "initial_cost": c0, "final_cost": 0.5 * opt.active_chi2()}
