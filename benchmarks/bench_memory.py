"""Memory of a run: peak RSS against the number of keyframes, and the memory per keyframe.

Each run is a separate ``mslam run`` process (so peak RSS is the run's own), on the built-in
synthetic ``loop`` at one resolution with ever more frames; the slope of peak RSS over the
number of keyframes is the memory one keyframe costs (its canonical pointmap, confidences,
descriptors, the graph edges it brings and the caches of the prior). Reported with the
figure expected from the arrays a keyframe holds at that resolution.

Usage: ``python benchmarks/bench_memory.py [--size 128x96] [--frames 24,48,72]``; rewrites the
"memory" section of RESULTS.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import table, write_section


def peak_rss_mib(frames: int, size: str) -> tuple[float, int, int]:
    """Run ``mslam run synthetic:loop:FRAMES:SIZE`` in a child process.

    Returns:
        (peak RSS in MiB of that child, keyframes, frames posed).
    """
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        code = (
            "import resource, sys; from mslam.cli import main; "
            f"rc = main(['run', 'synthetic:loop:{frames}:{size}', '--out', {str(out)!r}, "
            "'--quiet']); "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss); sys.exit(rc)"
        )
        res = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        )
        rss_kib = int(res.stdout.strip().splitlines()[-1])
        summary = json.loads((out / "summary.json").read_text())
    return rss_kib / 1024.0, summary["keyframes"], summary["frames_with_pose"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="128x96")
    ap.add_argument("--frames", default="24,48,72,96")
    args = ap.parse_args()
    rows, kfs, rss = [], [], []
    for n in (int(x) for x in args.frames.split(",")):
        mib, kf, posed = peak_rss_mib(n, args.size)
        rows.append([n, posed, kf, f"{mib:.0f}"])
        kfs.append(kf)
        rss.append(mib)
        print(rows[-1], flush=True)
    slope, intercept = np.polyfit(kfs, rss, 1)
    W, H = (int(v) for v in args.size.split("x"))
    # per pixel: X_canon (3), C (1), D (F = 24), Q (1), float64
    arrays = W * H * (3 + 1 + 24 + 1) * 8 / 2**20
    text = (
        f"`python benchmarks/bench_memory.py --size {args.size}`: one "
        "`mslam run` process per row (fast kernels, synthetic prior), peak RSS of that process.\n\n"
        + table(["frames", "posed", "keyframes", "peak RSS (MiB)"], rows)
        + f"\n\nLinear fit: **{slope:.2f} MiB per keyframe** at {args.size}, an upper bound: the "
        "fit gives the keyframes what the frames between them cost too (per-frame records, the "
        f"prior's caches up to their byte bound). Intercept "
        f"{intercept:.0f} MiB: Python, NumPy, Taichi and the compiled kernels. A keyframe's own "
        f"arrays (X_canon, C, D with F = 24, Q in float64) take {arrays:.2f} MiB at this size; "
        "the rest is its graph edges (idx, valid and Q per direction) and the prior's caches, "
        "which are bounded in bytes (`DescriptorConfig.cache_bytes`).\n"
    )
    print(text)
    write_section("memory", "Memory per keyframe", text)


if __name__ == "__main__":
    main()
