"""Benchmark of the device-resident entries (``mslam_fast.resident``) against the NumPy entries.

Per frame of the tracking chain at 512x384 and 224x160 (a synthetic ``loop`` pair through the
synthetic prior, as ``bench_matching.py``), the best of ``--repeat`` round-robin rounds of:

* matching through the API: ``mslam_fast.matching.match`` (NumPy in, NumPy out: on CUDA every
  argument is copied to the GPU and back) against ``ResidentMatcher.match`` (the keyframe's
  descriptors ``D21`` kept on the device; the frame's X11, X21, D11 uploaded per call; idx and
  valid downloaded), and the fused kernel alone on device copies (``ti.sync()`` after it);
* the parts of a matching call around the kernel, each alone: the host checks and conversion
  of its arrays, the upload of the frame's three arrays, the download of ``idx`` and ``valid``;
* fusion (``weighted_pointmap``): ``mslam_fast.fusion.update_pointmap`` against
  ``ResidentFusion.update_pointmap`` (the fused pointmap kept on the device between frames).

Both entries give the same results bit for bit (checked here on the timed pair too). On the CPU
a device array is the host array, so the two entries should take the same time; the figure
that matters is the CUDA one.

Usage: ``python benchmarks/bench_resident.py [--arch cpu|cuda] [--repeat N] [--no-write]``
(writes the RESULTS.md section ``resident-<arch>``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import table, write_section
from bench_matching import interleaved_best_ms, kernel_only, pair

from mslam_ref import fusion as ref_fusion
from mslam_ref.matching import MatchingConfig

SIZES = [(512, 384), (224, 160)]


def _sync() -> None:
    import taichi as ti

    ti.sync()


def rows_for(W: int, H: int, repeat: int) -> list[list[str]]:
    from mslam_fast import fusion, matching, resident

    X11, X21, D11, D21 = (np.ascontiguousarray(a) for a in pair(W, H))
    D21.setflags(write=False)  # a prior's cached keyframe descriptors
    cfg = MatchingConfig()
    matcher = resident.ResidentMatcher()
    a, b = matching.match(X11, X21, D11, D21), matcher.match(X11, X21, D11, D21)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)), "results differ"
    kernel, (d_idx, d_valid) = kernel_only(matching, X11, X21, D11, D21, cfg)
    args, _ = matching._match_args(X11, X21, D11, D21, None, cfg)

    def upload() -> None:
        for i in (0, 1, 2):
            resident.to_device(args[i], "bench.frame")
        _sync()

    fcfg = ref_fusion.FusionConfig("weighted_pointmap")
    X, C = X21.reshape(-1, 3), np.full(H * W, 2.0)
    state = {"numpy": ref_fusion.init_pointmap(X, C, fcfg)}
    state["resident"] = state["numpy"]
    fuser = resident.ResidentFusion()

    def fuse(key: str, fn) -> None:
        state[key] = fn(state[key], X, C, fcfg)

    runs = {
        "match (NumPy entry)": lambda: matching.match(X11, X21, D11, D21),
        "ResidentMatcher.match": lambda: matcher.match(X11, X21, D11, D21),
        "matching kernel only": kernel,
        "  host checks and conversion of the four arrays": lambda: matching._match_args(
            X11, X21, D11, D21, None, cfg
        ),
        "  upload of the frame's X11, X21, D11": upload,
        "  download of idx and valid": lambda: (resident.to_host(d_idx), resident.to_host(d_valid)),
        "update_pointmap (NumPy entry)": lambda: fuse("numpy", fusion.update_pointmap),
        "ResidentFusion.update_pointmap": lambda: fuse("resident", fuser.update_pointmap),
    }
    best = interleaved_best_ms(runs, repeat)
    return [[f"{W}x{H}", name, f"{ms:.2f}"] for name, ms in best.items()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", choices=["cpu", "cuda"], default="cpu", help="Taichi backend")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args()
    import mslam_fast

    mslam_fast.init(args.arch, "f64")
    rows = [r for W, H in SIZES for r in rows_for(W, H, args.repeat)]
    text = (
        f"`python benchmarks/bench_resident.py --arch {args.arch}`, float64, best of "
        f"{args.repeat} round-robin rounds (ms per call):\n\n"
        + table(["size", "entry", "ms"], rows)
        + "\n"
    )
    print(text)
    if not args.no_write:
        write_section(f"resident-{args.arch}", f"Device-resident entries ({args.arch})", text)


if __name__ == "__main__":
    main()
