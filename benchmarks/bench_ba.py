"""Bundle adjustment at cuda-bundle-adjustment's scale: mslam fast against native Ceres and g2o.

    python benchmarks/bench_ba.py [--repeat 3] [--iterations 10] [--only NAME ...]
                                  [--no-g2o] [--arch cpu|cuda] [--data DIR]

Problems (10 LM iterations each, the seed's benchmark length):

* ``ladybug49``: BAL Ladybug-49 (49 cameras, 7776 points, 31843 observations).
* ``kitti07`` / ``kitti00``: generated BAL problems of the size of the ORB-SLAM KITTI graphs
  (248 / 1332 poses, 26127 / 133383 points, about 95k / 561k observations;
  ``mslam_ref.ba.synthetic.make_forward_problem``, seed 1): a forward-moving camera, each point
  seen by a run of 2-12 consecutive views.
* ``kitti07-se3`` / ``kitti00-se3``: the same scenes as SE(3) + XYZ problems with monocular
  pinhole edges (g2o's ``EdgeProjectXYZ2UV``), against g2o.

Solvers: mslam fast (``LMConfig(iterations=10)``, Jacobi scaling on the BAL problems; the
Taichi kernels, the reduced system analysed once and refactored per trial); native Ceres
(``benchmarks/native/ceres_bal.cc``, SPARSE_SCHUR over SuiteSparse, 2 threads, all tolerances 0
so it runs its 10 iterations); g2o (``g2opy``: BlockSolverSE3 + LinearSolverEigen + Levenberg).

``--section`` names the RESULTS.md section (on a GPU machine: ``--arch cpu --section
ba-cuda-host`` then ``--arch cuda`` gives that machine's CPU and GPU figures side by side).

Timing: the solvers run in turn (A, B, A, B, ...), ``--repeat`` rounds, and the table reports
each one's median; other jobs share the 2 cores, so interleaving spreads their load over all
solvers alike.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: no spinning BLAS threads

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "reference"), str(ROOT / "fast"), str(ROOT / "benchmarks")]

import _ba_native as native  # noqa: E402
from _data import BAL_LADYBUG_49, data_dir  # noqa: E402
from _results import table, write_section  # noqa: E402

from mslam import bal as io  # noqa: E402
from mslam_ref.ba import lm, synthetic  # noqa: E402

SIZES = {"kitti07": (248, 26127, 3.64), "kitti00": (1332, 133383, 4.21)}
PROBLEMS = ("ladybug49", "kitti07", "kitti00", "kitti07-se3", "kitti00-se3")


def make_problem(name: str, data: Path):
    """The problem called ``name`` (see the module docstring)."""
    if name == "ladybug49":
        return io.read_bal(data / BAL_LADYBUG_49)
    base = name.removesuffix("-se3")
    model = "pinhole" if name.endswith("-se3") else "bal"
    return synthetic.make_forward_problem(*SIZES[base], model=model, seed=1)[0]


def run_fast(problem, kernels, iterations: int) -> dict:
    """One mslam solve: time, costs and the per-stage profile."""
    cfg = lm.LMConfig(iterations=iterations, jacobi_scaling=problem.cam_dof == 9)
    t0 = time.perf_counter()
    res = lm.optimize(problem, cfg, kernels)
    return {"time": time.perf_counter() - t0, "initial_cost": res.initial_cost,
            "final_cost": res.final_cost, "profile": res.profile,
            "trials": sum(h["trials"] for h in res.history)}  # fmt: skip


def interleaved(runners: dict, repeat: int) -> dict[str, list[dict]]:
    """Run every runner once per round, ``repeat`` rounds: {name: [result per round]}."""
    out: dict[str, list[dict]] = {k: [] for k in runners}
    for _ in range(repeat):
        for name, fn in runners.items():
            out[name].append(fn())
    return out


def median_run(runs: list[dict]) -> dict:
    """The run with the median time (its profile goes with it)."""
    return sorted(runs, key=lambda r: r["time"])[len(runs) // 2]


def bench_problem(name: str, args, kernels, ceres, tmp: Path) -> tuple[list[list], dict]:
    """Table rows and the fast solver's median profile for one problem."""
    problem = make_problem(name, Path(args.data))
    runners = {"mslam fast": lambda: run_fast(problem, kernels, args.iterations)}
    if problem.cam_dof == 9 and ceres is not None:
        f = tmp / f"{name}.txt"
        io.write_bal(problem, f)
        runners["native Ceres"] = lambda: native.run_ceres(ceres, f, args.iterations)
    if problem.cam_dof == 6 and not args.no_g2o:
        runners["g2o"] = lambda: native.run_g2o(problem, args.iterations)
    runs = interleaved(runners, args.repeat)
    med = {k: median_run(v) for k, v in runs.items()}
    other = next((k for k in med if k != "mslam fast"), None)
    rows = []
    for k, r in med.items():
        ratio = ""
        if other and k == "mslam fast":  # per round (A and B under the same load), then median
            paired = [a["time"] / b["time"] for a, b in zip(runs[k], runs[other])]
            ratio = f"{statistics.median(paired):.2f} ({', '.join(f'{x:.2f}' for x in paired)})"
        times = ", ".join(f"{x['time']:.2f}" for x in runs[k])
        rows.append([name, k, f"{r['time']:.3f}", times, ratio, f"{r['initial_cost']:.6g}",
                     f"{r['final_cost']:.8g}"])  # fmt: skip
    return rows, med["mslam fast"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--only", nargs="+", choices=PROBLEMS, default=list(PROBLEMS))
    ap.add_argument("--no-g2o", action="store_true")
    ap.add_argument("--arch", choices=["cpu", "cuda"], default="cpu", help="Taichi backend")
    ap.add_argument("--data", default=str(data_dir()), help="the data folder (Ladybug-49)")
    ap.add_argument("--section", help="RESULTS.md section (default: ba, or ba-cuda on CUDA)")
    args = ap.parse_args()
    import mslam_fast
    from mslam.kernels import load_kernels

    mslam_fast.init(args.arch, "f64")
    kernels = load_kernels("fast").ba
    for model in ("bal", "pinhole"):  # compile the kernels before timing
        tiny, _ = synthetic.make_forward_problem(4, 30, model=model)
        lm.optimize(tiny, lm.LMConfig(iterations=1, jacobi_scaling=model == "bal"), kernels)
    ceres = native.ceres_binary()
    rows, profiles = [], {}
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.only:
            r, prof = bench_problem(name, args, kernels, ceres, Path(tmp))
            rows += r
            profiles[name] = prof
            # written after every problem, so an interrupted run keeps what it measured
            write(rows, profiles, args, ceres is not None, (load0, os.getloadavg()[0]))


def write(rows, profiles, args, have_ceres: bool, load: tuple[float, float]) -> None:
    """Print and write the RESULTS.md section."""
    header = ["problem", "solver", "median s", "runs (s, in order)", "fast / other (per round)",
              "initial cost", "final cost"]  # fmt: skip
    body = table(header, rows)
    stages = list(lm.PROFILE_KEYS)
    prof_rows = []
    for name, p in profiles.items():
        total = sum(p["profile"].values())
        cells = [f"{1e3 * p['profile'][s]:.0f}" for s in stages]
        share = p["profile"]["numerical_decomposition"] / total
        prof_rows.append([name, *cells, f"{100 * share:.0f} %", p["trials"]])
    body += (
        f"\n\n{args.iterations} LM iterations per solver; {args.repeat} interleaved rounds "
        "(each solver in turn), the median time reported; the ratio is the median of the "
        "per-round ratios (the two solves of a round ran back to back). Load average "
        f"{load[0]:.1f} -> {load[1]:.1f} during the run: other jobs share the 2 cores, so every "
        "figure may be pessimistic, but the solvers shared the load alike. "
        + ("" if have_ceres else "Native Ceres was not built (no g++ or libceres-dev). ")
        + "Costs are 0.5 sum |r|^2 (Ceres' convention; g2o's chi2 / 2). An iteration of Ceres "
        "is one linear solve, accepted or not; an iteration of mslam and g2o is one accepted "
        "step (up to 10 solves), so mslam's solve count is the profile's trials column.\n\n"
        "mslam fast per-stage profile of the median run (ms; symbolic decomposition runs once "
        "per solve, numerical decomposition once per trial):\n\n"
        + table(["problem", *stages, "numerical / total", "trials"], prof_rows)
    )
    print(body, flush=True)
    name = args.section or ("ba" if args.arch == "cpu" else "ba-cuda")
    where = "CPU" if args.arch == "cpu" else "CUDA"
    write_section(
        name, f"Bundle adjustment (Ladybug-49, KITTI-sized), fast kernels on {where}", body
    )


if __name__ == "__main__":
    main()
