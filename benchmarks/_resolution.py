"""``bench_system.py --resolution N``: the whole system at one working resolution, per kernel set.

Each configuration runs in its own process (``profile_system.py --json``) so that its peak
memory is its own: the fast kernels in float64 (the default) and float32, the fast kernels
with the background backend (``single_thread=false``), and the reference kernels on the first
``ref_frames`` frames only (NumPy matching costs seconds per 512x384 pair).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from _results import table
from profile_system import flatness

HERE = Path(__file__).resolve().parent

#: (label, kernels, extra profile_system arguments)
RUNS = (
    ("fast, f64", "fast", ["--precision", "f64"]),
    ("fast, f32", "fast", ["--precision", "f32"]),
    (
        "fast, f64, background backend",
        "fast",
        ["--precision", "f64", "--set", "single_thread=false"],
    ),
    ("ref", "ref", []),
)


def run_profile(
    long_side: int, kernels: str, extra: list[str], frames: int | None, config: str, data: Path
) -> dict:
    """One ``profile_system.py`` run in a fresh process; returns its JSON figures."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.json"
        cmd = [sys.executable, str(HERE / "profile_system.py"), "--long-side", str(long_side)]
        cmd += ["--config", config, "--data", str(data)]
        cmd += ["--kernels", kernels, *extra, "--json", str(out)]
        if frames:
            cmd += ["--frames", str(frames)]
        subprocess.run(cmd, check=True)
        return json.loads(out.read_text())


def summary_row(label: str, r: dict) -> list[str]:
    """One row of the comparison table."""
    t, total = r["times"], r["seconds"]
    first, last = sum(t[:30]) / len(t[:30]), sum(t[-30:]) / len(t[-30:])
    top = max(r["stages"].items(), key=lambda kv: kv[1])
    plain, kf = flatness(r)
    return [
        label,
        f"{r['frames']}",
        f"{r['posed']}",
        f"{r['keyframes']}",
        f"{r['frames'] / total:.2f}",
        f"{100 * r['ate_m']:.2f}",
        f"{r['rss_mib']:.0f}",
        f"{last / first:.2f} ({plain:.2f}, {kf:.2f})",
        f"{top[0]} {100 * top[1] / total:.0f} %",
    ]


def stage_table(runs: list[tuple[str, dict]]) -> str:
    """Share of the frame time per stage (columns: the runs)."""
    names = sorted({k for _, r in runs for k in r["stages"]})
    order = sorted(names, key=lambda k: -runs[0][1]["stages"].get(k, 0.0))
    rows = []
    for k in order:
        rows.append(
            [k] + [f"{100 * r['stages'].get(k, 0.0) / r['seconds']:.0f} %" for _, r in runs]
        )
    return table(["stage"] + [label for label, _ in runs], rows)


def prior_step_table(runs: list[tuple[str, dict]]) -> str:
    """Milliseconds per frame of the prior's sub-steps (columns: the runs)."""
    names = sorted({k for _, r in runs for k in r.get("prior_steps", {})})
    first = runs[0][1].get("prior_steps", {})
    rows = []
    for k in sorted(names, key=lambda k: -first.get(k, 0.0)):
        cells = [
            f"{1000 * r.get('prior_steps', {}).get(k, 0.0) / r['frames']:.1f}" for _, r in runs
        ]
        rows.append([k, *cells])
    return table(["prior sub-step [ms/frame]"] + [label for label, _ in runs], rows)


def resolution_bench(
    long_side: int, frames: int | None, ref_frames: int, config: str, data: Path
) -> str:
    """Run :data:`RUNS` at ``long_side`` with ``config`` on the 7-Scenes clip of the data folder
    ``data``; returns the Markdown for RESULTS.md."""
    runs = []
    for label, kernels, extra in RUNS:
        n = ref_frames if kernels == "ref" else frames
        if kernels == "ref" and ref_frames <= 0:
            continue
        r = run_profile(long_side, kernels, extra, n, config, data)
        runs.append((label if n is None else f"{label} (first {n} frames)", r))
        print(label, {k: r[k] for k in ("frames", "posed", "seconds", "ate_m", "rss_mib")})
    size = runs[0][1]["size"]
    header = ["kernels", "frames", "posed", "keyframes", "frames/s", "ATE [cm]",
              "peak RSS [MiB]", "last 30 / first 30", "largest stage"]  # fmt: skip
    return (
        f"7-Scenes redkitchen frames 0-149, RGB-D prior (`--config {config}`), {size} "
        f"(`--set dataset.long_side={long_side}`), one process per row, Taichi kernels compiled "
        "beforehand. `frames/s` counts the whole run including every graph step and solve; "
        "`last 30 / first 30` compares the mean frame times at the end and the start (in "
        "brackets: the same for the frames that did not become keyframes, and last 3 / first 3 "
        "for the frames that did, which carry the graph step and the solve: a cost that grows "
        "with the map shows there, keyframes that are denser at the end only in the first).\n\n"
        + table(header, [summary_row(label, r) for label, r in runs])
        + "\n\nShare of the frame time per stage (the system's timers; with the background "
        "backend, `graph` and `backend` run beside the frontend, so shares can sum past 100 %):"
        "\n\n" + stage_table(runs) + "\n\nThe prior's sub-steps (RGBDPrior's timers over all its "
        "calls: tracking, graph edges, relocalisation), milliseconds per frame:\n\n"
        + prior_step_table(runs)
        + "\n"
    )
