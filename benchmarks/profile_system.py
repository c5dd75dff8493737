"""Where the time of a real run goes: frames per second, the stage table, frame time over the
sequence, peak memory.

Runs the 7-Scenes clip (redkitchen frames 0-149, ``--data``) with the RGB-D prior and the
chosen kernel set at a working resolution (``dataset.long_side``), frame by frame, and reports:

* frames per second over the run, and the share of each stage (the system's own timers:
  prior, matching, tracking, fusion, graph, backend, ...) in the frame time;
* the mean frame time of the first and the last 30 frames (a flat run has a ratio near 1);
* the peak resident memory of the process.

Usage: ``python benchmarks/profile_system.py --long-side 512 [--frames 40] [--kernels fast]
[--precision f32] [--arch cpu|cuda] [--set KEY=VALUE] [--json OUT] [--data DIR]``; writes the
section ``profile-<long_side>-<frames>-<kernels>`` (``-cuda`` appended on CUDA) of RESULTS.md
(or the figures as JSON to OUT, which is how ``bench_system.py --resolution`` runs one
profile per process).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _data import add_data_argument, seven_scenes
from _results import table, write_section

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source
from mslam.system.frontend import SlamSystem
from mslam.system.outputs import evaluate_run


def profile(
    long_side: int,
    frames: int | None,
    kernels: str,
    overrides=(),
    config: str = "rgbd",
    clip: Path | None = None,
) -> dict:
    """One run, frame by frame; returns FPS, stage seconds, frame times, ATE and peak RSS."""
    cfg = load_config(config, [f"dataset.long_side={long_side}", *overrides])
    src = open_source(str(clip or seven_scenes()), cfg, max_frames=frames)
    system = SlamSystem(src.prior, cfg, load_kernels(kernels), src.K)
    times, statuses = [], []
    for i in range(len(src.sequence)):
        frame = src.sequence[i]
        t0 = time.perf_counter()
        statuses.append(system.process(frame))
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    system.close()  # the background backend's queued keyframes count too
    times[-1] += time.perf_counter() - t0
    H, W = src.sequence[0].shape
    ev = evaluate_run(system, src.sequence)
    return {
        "ate_m": ev.get("ate", {}).get("ate_rmse", float("nan")),
        "size": f"{W}x{H}",
        "frames": len(times),
        "posed": len(system.frame_poses()[0]),
        "keyframes": len(system.keyframes),
        "seconds": sum(times),
        "stages": dict(system.stats.seconds),
        # The RGB-D prior's own timers (SIFT, ratio test, PnP, ICP, ...): the sub-steps of the
        # ``prior`` stage and of the prior calls inside ``graph`` and ``reloc``.
        "prior_steps": dict(getattr(src.prior, "seconds", {})),
        "times": times,
        "statuses": statuses,
        "rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def flatness(r: dict) -> tuple[float, float]:
    """Growth of the cost with the map: mean time of frames that did not become keyframes
    (last 30 / first 30 such frames), and of the frames that did (last 3 / first 3 after
    the first keyframe: their graph step and solve)."""
    t, st = r["times"], r["statuses"]
    plain = [x for x, s in zip(t, st, strict=True) if s != "keyframe"]
    kf = [x for x, s in zip(t, st, strict=True) if s == "keyframe"][1:]
    ratio = lambda a, n: (sum(a[-n:]) / len(a[-n:])) / (sum(a[:n]) / len(a[:n])) if a else 0.0
    return ratio(plain, 30), ratio(kf, 3)


def report(r: dict, command: str) -> str:
    """The Markdown paragraph and stage table of one profile."""
    total = r["seconds"]
    stages = sorted(r["stages"].items(), key=lambda kv: -kv[1])
    rows = [[k, f"{v:.1f}", f"{100 * v / total:.0f} %"] for k, v in stages]
    rows.append(["(outside the timers)", f"{total - sum(r['stages'].values()):.1f}", ""])
    t = r["times"]
    first, last = sum(t[:30]) / len(t[:30]), sum(t[-30:]) / len(t[-30:])
    steps = sorted(r.get("prior_steps", {}).items(), key=lambda kv: -kv[1])
    sub = [[k, f"{v:.1f}", f"{1000 * v / r['frames']:.1f}"] for k, v in steps]
    return (
        f"`{command}`: 7-Scenes redkitchen, RGB-D prior, {r['size']}, {r['frames']} frames "
        f"({r['posed']} posed, {r['keyframes']} keyframes): **{r['frames'] / total:.2f} "
        f"frames/s**, ATE {100 * r['ate_m']:.2f} cm, peak RSS {r['rss_mib']:.0f} MiB; mean frame "
        f"time {first:.2f} s over the first 30 frames, {last:.2f} s over the last 30 "
        f"(ratio {last / first:.2f}).\n\n"
        + table(["stage", "seconds", "share of frame time"], rows)
        + "\n\nSub-steps of the prior (its calls in every stage):\n\n"
        + table(["sub-step", "seconds", "ms per frame"], sub)
        + "\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long-side", type=int, default=512)
    ap.add_argument("--frames", type=int, default=None, help="first N frames (default: all 150)")
    ap.add_argument("--kernels", default="fast", choices=("ref", "fast"))
    ap.add_argument("--precision", default="f64", choices=("f64", "f32"), help="fast kernels")
    ap.add_argument("--arch", default="cpu", choices=("cpu", "cuda"), help="fast kernels")
    ap.add_argument("--config", default="rgbd", help="config file or packaged name (rgbd_512)")
    ap.add_argument("--set", action="append", default=[], help="config override KEY=VALUE")
    ap.add_argument("--json", type=Path, help="write the figures here instead of RESULTS.md")
    add_data_argument(ap)
    args = ap.parse_args()
    clip = seven_scenes(args.data)
    if not clip.is_dir():
        sys.exit(f"profile_system: the 7-Scenes clip is not at {clip} (set --data or MSLAM_DATA)")
    if args.kernels == "fast":
        import mslam_fast

        mslam_fast.init(args.arch, args.precision)
        # Compile the kernels first, with the run's settings (some are compile-time constants).
        profile(64, 6, "fast", args.set, args.config, clip)
    r = profile(args.long_side, args.frames, args.kernels, args.set, args.config, clip)
    if args.json is not None:
        args.json.write_text(json.dumps(r))
        return
    prec = f" --precision {args.precision}" if args.kernels == "fast" else ""
    command = (
        f"python benchmarks/profile_system.py --long-side {args.long_side}"
        f"{f' --frames {args.frames}' if args.frames else ''} --kernels {args.kernels}{prec}"
        + (f" --arch {args.arch}" if args.arch != "cpu" else "")
        + (f" --config {args.config}" if args.config != "rgbd" else "")
        + "".join(f" --set {o}" for o in args.set)
    )
    text = report(r, command)
    print(text)
    name = f"profile-{args.long_side}-{args.frames or 'all'}-{args.kernels}{prec.split()[-1] if prec else ''}"
    name += "-cuda" if args.arch == "cuda" else ""
    where = " on CUDA" if args.arch == "cuda" else ""
    write_section(name, f"Stage profile, {r['size']}, {args.kernels} kernels{where}", text)


if __name__ == "__main__":
    main()
