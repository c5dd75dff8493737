"""Benchmark: one tracking linearisation and one backend directed block at 512x384.

Reference (NumPy, float64) against the Taichi kernels on the CPU (f64 and f32), uncalibrated
(ray + distance) and calibrated (pixel + log-depth). Best of N wall times after a warm-up
call (the first call compiles the kernel). Writes the ``tracking`` section of RESULTS.md.

    python benchmarks/bench_tracking.py [--repeat 10] [--arch cpu|cuda]

``--arch cuda`` (a GPU) writes the section ``tracking-cuda`` instead; its times include the
copies of the NumPy inputs and outputs between host and GPU, as a caller of these functions
pays them.
"""

from __future__ import annotations

import argparse
import os
import warnings

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
warnings.filterwarnings("ignore")

import numpy as np  # noqa: E402
from _results import best_of, table, write_section  # noqa: E402

from mslam_ref import backend as ref_backend  # noqa: E402
from mslam_ref import sim3  # noqa: E402
from mslam_ref import tracking as ref_tracking  # noqa: E402
from mslam_ref.pointmap import backproject  # noqa: E402

H, W = 384, 512
K = np.array([[400.0, 0.0, 255.5], [0.0, 400.0, 191.5], [0.0, 0.0, 1.0]])


def problem():
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:H, 0:W]
    X_k = backproject(2.0 + 0.3 * np.sin(u / 40.0) + 0.2 * np.cos(v / 30.0), K)
    T = sim3.exp(np.array([0.05, -0.03, 0.02, 0.02, -0.03, 0.01, 0.05]))
    X_f = sim3.act(sim3.inv(T), X_k.reshape(-1, 3)) + rng.normal(0, 0.01, (H * W, 3))
    Q = rng.uniform(1.0, 3.0, H * W)
    valid = rng.random(H * W) < 0.9
    # backend: two keyframes, one directed block (1 <- 0) with the same correspondences
    T_WC = np.stack([sim3.identity(), sim3.inv(T)])
    X = np.stack([X_k, X_f.reshape(H, W, 3)])
    C = np.full((2, H, W), 2.0)
    blk = (np.array([1]), np.array([0]), np.arange(H * W)[None], valid[None], Q[None])
    graphs = (ref_backend.PoseGraph(X, C, *blk), ref_backend.PoseGraph(X, C, *blk, K_cam=K))
    return T, X_f, X_k, Q, valid, T_WC, graphs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--arch", choices=["cpu", "cuda"], default="cpu", help="Taichi backend")
    args = ap.parse_args()
    import mslam_fast
    from mslam_fast import backend as fast_backend
    from mslam_fast import tracking as fast_tracking

    T, X_f, X_k, Q, valid, T_WC, (graph, graph_cal) = problem()
    cases = {
        "tracking linearize, ray+dist": lambda m: lambda: m[0].linearize(T, X_f, X_k, Q, valid),
        "tracking linearize, calibrated": lambda m: (
            lambda: m[0].linearize(T, X_f, X_k, Q, valid, ref_tracking.TrackingConfig(), K)
        ),
        "backend 1 block, ray+dist": lambda m: lambda: m[1].linearize(T_WC, graph),
        "backend 1 block, calibrated": lambda m: lambda: m[1].linearize(T_WC, graph_cal),
    }
    times: dict[str, dict[str, float]] = {name: {} for name in cases}
    for name, make in cases.items():
        times[name]["ref"] = best_of(
            make((ref_tracking, ref_backend)), repeat=max(3, args.repeat // 3)
        )
    for fp in ("f64", "f32"):
        mslam_fast.init(args.arch, fp)
        for name, make in cases.items():
            times[name][fp] = best_of(
                make((fast_tracking, fast_backend)), repeat=args.repeat, warmup=2
            )
    rows = []
    for name, t in times.items():
        rows.append(
            [
                name,
                f"{t['ref'] * 1e3:.1f}",
                f"{t['f64'] * 1e3:.2f}",
                f"{t['f32'] * 1e3:.2f}",
                f"{t['ref'] / t['f64']:.0f}x",
                f"{t['ref'] / t['f32']:.0f}x",
            ]
        )
    where = "Taichi on the CPU" if args.arch == "cpu" else _gpu_name()
    body = (
        f"{W}x{H} = {H * W} pixels, 90 % valid; best of {args.repeat} (reference: best of "
        f"{max(3, args.repeat // 3)}) after warm-up; times in ms; fast kernels: {where}.\n\n"
        + table(["case", "reference", "fast f64", "fast f32", "speed-up f64", "speed-up f32"], rows)
    )
    if args.arch == "cpu":
        write_section("tracking", "Tracking and backend linearisation", body)
    else:
        write_section("tracking-cuda", "Tracking and backend linearisation on CUDA", body)
    print(body)


def _gpu_name() -> str:
    """The GPU's name from nvidia-smi, for the section's text."""
    import subprocess

    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20)
        return f"Taichi on CUDA, {out.stdout.strip().splitlines()[0]}"
    except (OSError, IndexError, subprocess.SubprocessError):
        return "Taichi on CUDA"


if __name__ == "__main__":
    main()
