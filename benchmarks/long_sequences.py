"""Long sequences: does a run hold over 600-1000 frames, and what grows with the map?

Runs ``mslam.run`` (the command line's behaviour: packaged config by prior, outputs) on one
source and records, beside ``summary.json``:

* the wall time of every frame (``SlamSystem.process``) and the frames/s of the first and the
  last quarter of the frames;
* every backend step (a new keyframe): keyframes and edges in the map, the seconds of its graph
  construction and of its global solve, the keyframes the solve moved;
* the keyframe count after each quarter of the frames (revisits should add few);
* the error after each quarter under the one Sim(3) of the whole run, and each quarter's own
  Sim(3) scale relative to the first quarter's (scale drift);
* revisit consistency: frames with the same ground-truth pose (a variant that plays the clip
  back and forth) should get the same estimate; the RMS spread of their aligned positions;
* the process's peak resident memory.

Usage: ``python benchmarks/long_sequences.py SOURCE --out RUN [--prior twoview] [--calib FILE]
[--set KEY=VALUE ...]``; writes ``RUN/long.json`` and prints one table row. Long variants of the
7-Scenes clip: ``python benchmarks/video_variants.py DIR --only pingpong2 loop3 mixed``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import resource
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

import mslam
from mslam.evaluate import associate, umeyama
from mslam.system.frontend import SlamSystem
from mslam.system.global_opt import Backend


class Recorder:
    """Times ``SlamSystem.process`` and ``Backend.step`` / ``Backend.solve`` by wrapping them."""

    def __init__(self) -> None:
        self.frames: list[dict[str, Any]] = []
        self.steps: list[dict[str, Any]] = []
        self._solve_s = 0.0

    def install(self) -> None:
        process, step, solve = SlamSystem.process, Backend.step, Backend.solve
        rec = self

        def timed_process(system: SlamSystem, frame: Any) -> Any:
            t0 = time.perf_counter()
            status = process(system, frame)
            rec.frames.append(
                {
                    "s": time.perf_counter() - t0,
                    "status": str(status),
                    "kf": len(system.keyframes),
                }
            )
            return status

        def timed_solve(backend: Backend) -> Any:
            t0 = time.perf_counter()
            try:
                return solve(backend)
            finally:
                rec._solve_s = time.perf_counter() - t0

        def timed_step(backend: Backend, k: int, known: Any = None) -> None:
            before = len(backend.graph)
            T0 = backend.keyframes.poses()
            t0 = time.perf_counter()
            rec._solve_s = 0.0
            step(backend, k, known)
            T1 = backend.keyframes.poses()
            moved = np.linalg.norm(T1[: len(T0), :3] - T0[:, :3], axis=1)
            rec.steps.append(
                {
                    "k": int(k),
                    "keyframes": len(backend.keyframes),
                    "edges": len(backend.graph),
                    "added": len(backend.graph) - before,
                    "seconds": time.perf_counter() - t0,
                    "solve_s": rec._solve_s,
                    "moved": int(np.sum(moved > 1e-9)),
                }
            )

        SlamSystem.process = timed_process  # type: ignore[method-assign]
        Backend.step = timed_step  # type: ignore[method-assign]
        Backend.solve = timed_solve  # type: ignore[method-assign]


def quarters(n: int) -> list[slice]:
    """Four consecutive slices covering ``range(n)``."""
    edges = np.linspace(0, n, 5).round().astype(int)
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges)]


def drift_figures(result: Any) -> dict[str, Any]:
    """Per-quarter error and scale, and revisit spread (module docstring); {} without truth."""
    seq = result.source.sequence
    if seq.T_WC is None:
        return {}
    gt = np.asarray(seq.T_WC, np.float64)
    _, ts, T = result.trajectory
    ie, ig = associate(ts, np.asarray(seq.timestamps, np.float64))
    p_est, p_gt = T[ie, :3], gt[ig, :3]
    R, t, s = umeyama(p_est, p_gt)
    aligned = s * p_est @ R.T + t
    err = np.linalg.norm(aligned - p_gt, axis=1)
    out: dict[str, Any] = {"quarter_ate_cm": [], "quarter_scale": []}
    s0 = None
    for q in quarters(len(ie)):
        out["quarter_ate_cm"].append(100 * float(np.sqrt(np.mean(err[q] ** 2))))
        sq = umeyama(p_est[q], p_gt[q])[2] if q.stop - q.start >= 3 else float("nan")
        s0 = sq if s0 is None else s0
        out["quarter_scale"].append(float(sq / s0))
    groups: dict[tuple[float, ...], list[int]] = defaultdict(list)
    for n, g in enumerate(gt[ig]):
        groups[tuple(np.round(g[:7], 6))].append(n)
    spread = [aligned[m] - aligned[m].mean(0) for m in groups.values() if len(m) > 1]
    if spread:
        d = np.concatenate(spread)
        out["revisit_spread_cm"] = 100 * float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
    return out


def figures(result: Any, rec: Recorder) -> dict[str, Any]:
    """Everything the table row reports."""
    s = result.summary
    t = np.array([f["s"] for f in rec.frames])
    kf = [f["kf"] for f in rec.frames]
    qs = quarters(len(t))
    steps = rec.steps
    head, tail = steps[: max(1, len(steps) // 4)], steps[-max(1, len(steps) // 4) :]
    mean = lambda xs, key: float(np.mean([x[key] for x in xs])) if xs else float("nan")
    return {
        "source": s["source"],
        "frames": s["frames"],
        "posed": s["frames_posed_fraction"],
        "ate_cm": None if s.get("ate_rmse") is None else 100 * s["ate_rmse"],
        "keyframes": s["keyframes"],
        "keyframes_per_quarter": [kf[q.stop - 1] for q in qs],
        "edges": s["edges"],
        "loop_edges": s["loop_closure_edges"],
        "longest_span": s["longest_loop_closure_span"],
        "unverified": s.get("loop_closure_candidates_unverified"),
        "fps": s["frames_per_second"],
        "fps_quarters": [float((q.stop - q.start) / t[q].sum()) for q in qs],
        "step_s_first_last": [mean(head, "seconds"), mean(tail, "seconds")],
        "solve_s_first_last": [mean(head, "solve_s"), mean(tail, "solve_s")],
        "stage_seconds": s["stage_seconds"],
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "plausible": s["plausible"],
        "warnings": s["warnings"],
        "maps": len(s.get("maps") or []) or 1,
        "steps": steps,
        **drift_figures(result),
    }


def row(f: dict[str, Any]) -> str:
    """One line of the figures."""
    ate = "-" if f["ate_cm"] is None else f"{f['ate_cm']:.2f} cm"
    fq = " / ".join(f"{x:.2f}" for x in f["fps_quarters"])
    kq = "/".join(str(k) for k in f["keyframes_per_quarter"])
    text = (
        f"{f['source']}: {f['frames']} frames, posed {100 * f['posed']:.1f} %, ATE {ate}, "
        f"keyframes {f['keyframes']} (by quarter {kq}), edges {f['edges']} "
        f"(loop {f['loop_edges']}, span {f['longest_span']}, unverified {f['unverified']}), "
        f"{f['fps']:.2f} frames/s (quarters {fq}), backend step {f['step_s_first_last'][0]:.2f}"
        f" -> {f['step_s_first_last'][1]:.2f} s (solve {f['solve_s_first_last'][0]:.2f} -> "
        f"{f['solve_s_first_last'][1]:.2f} s), peak RSS {f['peak_rss_mib']:.0f} MiB, "
        f"plausible {f['plausible']}, warnings {f['warnings']}"
    )
    if "quarter_ate_cm" in f:
        text += (
            ", ATE by quarter "
            + "/".join(f"{x:.2f}" for x in f["quarter_ate_cm"])
            + " cm, scale by quarter "
            + "/".join(f"{x:.3f}" for x in f["quarter_scale"])
        )
    if "revisit_spread_cm" in f:
        text += f", revisit spread {f['revisit_spread_cm']:.2f} cm"
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--prior", default=None)
    ap.add_argument("--calib", default=None)
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", dest="settings", action="append", default=[])
    ap.add_argument("--table", action="store_true", help="print the row of an existing RUN")
    args = ap.parse_args(argv)
    if args.table:
        print(row(json.loads((args.out / "long.json").read_text())))
        return 0
    rec = Recorder()
    rec.install()
    result = mslam.run(
        args.source,
        args.out,
        config=args.config,
        prior=args.prior,
        calib=args.calib,
        settings=args.settings,
        overwrite=True,
        progress=True,
    )
    f = figures(result, rec)
    (args.out / "long.json").write_text(json.dumps(f, indent=1))
    print(row(f))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
