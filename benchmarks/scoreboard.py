"""One table for the RGB-only path on every video this repository can make: the scoreboard.

Writes the variants of ``video_variants.py`` and ``hard_variants.py`` (from the shared 7-Scenes
clip) into ``WORK/inputs``, runs ``mslam run SOURCE --prior twoview --quiet`` on each of them,
on the clip itself (uncalibrated and with its ``calib.yaml``) and on the built-in synthetic
paths, ``--jobs`` runs at a time, and tabulates each run's ``summary.json``: frames, posed
share, ATE, keyframes, frames per second, the verdict (``plausible``) and its warnings, and the
trajectory's checksum (a change of code that should not move any trajectory keeps them all).
The clip's own runs and the RGB-D default run also get the dense-map metrics of ``mslam eval
--map --truth-rgbd`` (chamfer under the trajectory's Sim(3) and after ``--map-icp``). So do the
clip re-rendered with exact depth (``novel_views.py --depth``, 320x240, 55°) along its own path
(``rendered still``) and along one that weaves off it (``rendered weave``), each RGB only
(uncalibrated and calibrated) and RGB-D: there the truth is exact, so their chamfers track the
map rather than the ground truth's own error.

Frames per second are measured ``--jobs`` at a time and are lower than a run alone (the clip:
2.9 with two jobs on 2 cores, 4.4–4.6 alone in RESULTS.md).

Usage: ``python benchmarks/scoreboard.py [WORK] [--only NAME ...] [--long] [--jobs 2]
[--no-write]``; writes the section ``scoreboard`` of RESULTS.md unless ``--no-write`` or
``--only``. ``--long`` adds the 895- and 648-frame replays (``loop3``, ``mixed``). About 35 min
for the default set with two jobs on 2 cores, the renderings included (2026-11-27).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import hard_variants
import novel_views
import video_variants
from _results import git_rev, table, write_section

CLIP = video_variants.CLIP

#: Reorderings of the clip (``video_variants.py``); ``NAMEcal`` runs with its ``calib.yaml``.
VIDEO = ["rev", "every2", "every3", "every4", "every3rev", "pingpong", "crop", "revcal",
         "every2cal"]  # fmt: skip
#: The long replays, with ``--long`` only.
LONG = ["loop3", "mixed"]
#: Built-in synthetic paths (name, source).
SYNTHETIC = ["loop", "detour", "rotation", "forward:120:160x120", "jump"]

#: Paths of the clip re-rendered with depth (``novel_views.py``), and their lens and size.
RENDERED = ["still", "weave"]
RENDER_FOV, RENDER_SIZE = 55.0, (320, 240)

#: Columns of the RESULTS table.
HEADER = ["input", "frames", "posed %", "ATE [cm]", "keyframes", "frames/s", "plausible",
          "maps", "map chamfer: traj. / ICP [cm]", "spread watch", "warnings",
          "trajectory"]  # fmt: skip


def inputs(
    work: Path, clip: Path, long: bool, only: list[str] | None = None
) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
    """Every run of the scoreboard, RGB only and RGB-D: name -> ``mslam run`` arguments
    (source first); writes the variants' folders under ``work / "inputs"`` (the renderings
    only when ``only`` is None or names one of their runs)."""
    out = work / "inputs"
    runs: dict[str, list[str]] = {
        "clip": [str(clip)],
        "clip, calibrated": [str(clip), "--calib", str(clip / "calib.yaml")],
    }
    for name in VIDEO + (LONG if long else []):
        base = name.removesuffix("cal")
        folder = video_variants.write_variant(clip, out, base)
        runs[name] = [str(folder)] + (
            ["--calib", str(folder / "calib.yaml")] if base != name else []
        )
    for name in hard_variants.NAMES:
        runs[name] = [str(hard_variants.write_variant(clip, out, name))]
    for name in SYNTHETIC:
        runs[f"synthetic:{name}"] = [f"synthetic:{name}"]
    rgbd = {"clip, RGB-D default": [str(clip)]}
    for path in RENDERED:
        name = f"rendered {path}"
        if only is not None and not any(n.startswith(name) for n in only):
            continue
        folder = rendered(out, clip, path)
        runs[name] = [str(folder)]
        runs[f"{name}, calibrated"] = [str(folder), "--calib", str(folder / "calib.yaml")]
        rgbd[f"{name}, RGB-D default"] = [str(folder)]
    return runs, rgbd


def rendered(out: Path, clip: Path, path: str) -> Path:
    """The clip re-rendered along ``path`` with depth into ``out / f"rendered_{path}"``
    (written once: about 3 minutes each)."""
    folder = out / f"rendered_{path}"
    if not (folder / "depth.txt").exists():
        novel_views.write_video(folder, clip, path, RENDER_FOV, 1, RENDER_SIZE, depth=True)
    return folder


def truth_folder(name: str, argv: list[str], clip: Path) -> Path | None:
    """The RGB-D folder a run's map is scored against: the clip for the clip's own runs, the
    rendering for the rendered ones, else None."""
    if name.startswith("clip"):
        return clip
    return Path(argv[0]) if name.startswith("rendered") else None


def run_one(work: Path, name: str, argv: list[str], prior: str | None = "twoview") -> Path:
    """``mslam run`` of one input into ``work / "runs" / name`` (``prior`` None: the source's
    default); returns the run folder."""
    out = work / "runs" / name.replace(" ", "_").replace(",", "").replace(":", "_")
    cmd = ["mslam", "run", *argv, *(["--prior", prior] if prior else [])]
    cmd += ["--out", str(out), "--quiet", "--overwrite"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        (out.parent / f"{out.name}.err").write_text(done.stderr)
    print(f"{name}: exit {done.returncode}", flush=True)
    return out


def map_chamfers(run: Path, truth: Path) -> str:
    """``traj. / ICP`` chamfer (cm) of a run against the RGB-D folder ``truth``, by ``mslam
    eval``."""
    got = []
    for extra in ([], ["--map-icp"]):
        cmd = ["mslam", "eval", str(truth / "groundtruth.txt"), str(run / "trajectory.txt"),
               "--map", str(run / "reconstruction.ply"), "--truth-rgbd", str(truth), *extra]  # fmt: skip
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            return "–"
        d = json.loads(done.stdout)
        got.append(f"{100 * d.get('map', d)['chamfer']:.1f}")
    return " / ".join(got)


def row(name: str, run: Path, chamfer: str) -> list[object]:
    """One table row from a run's outputs (a failed run: its error's first line)."""
    if not (run / "summary.json").exists():
        err_file = run.parent / f"{run.name}.err"
        err = err_file.read_text().strip() if err_file.exists() else "no summary.json"
        return [name, "–", "–", "–", "–", "–", "failed", "–", "–", "–", err[:80], "–"]
    s = video_variants.read_summary(run)
    md5 = hashlib.md5((run / "trajectory.txt").read_bytes()).hexdigest()[:8]
    warnings = "; ".join(w[:70] for w in s["warnings"]) or "–"
    return [name, s["frames"], f"{s['posed_pct']:.1f}", s["ate_cm"], s["keyframes"],
            f"{s['frames_per_second']:.2f}", s["plausible"], hard_variants.maps_text(s),
            chamfer, video_variants.spread_text(s), warnings, f"`{md5}`"]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("work", type=Path, nargs="?", default=Path("/tmp/mslam_scoreboard"))
    ap.add_argument("--clip", type=Path, default=CLIP)
    ap.add_argument("--only", nargs="*", default=None, help="names of the table's first column")
    ap.add_argument("--long", action="store_true", help="add the long replays loop3 and mixed")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    if not args.clip.is_dir():
        print(f"{args.clip}: clip folder not found", file=sys.stderr)
        return 2
    runs, rgbd = inputs(args.work, args.clip, args.long, args.only)
    if args.only is not None:
        unknown = sorted(set(args.only) - set(runs) - set(rgbd))
        if unknown:
            known = ", ".join([*runs, *rgbd])
            print(f"--only: unknown {', '.join(unknown)}; known: {known}", file=sys.stderr)
            return 2
        runs = {k: v for k, v in runs.items() if k in args.only}
        rgbd = {k: v for k, v in rgbd.items() if k in args.only or k.startswith("clip")}
    with ThreadPoolExecutor(args.jobs) as pool:
        done = dict(zip(runs, pool.map(lambda kv: run_one(args.work, *kv), runs.items())))
        done.update(zip(rgbd, pool.map(lambda kv: run_one(args.work, *kv, None), rgbd.items())))
    rows = []
    argvs = {**runs, **rgbd}
    for name, run in done.items():
        truth = truth_folder(name, argvs[name], args.clip)
        ok = truth is not None and (run / "summary.json").exists()
        rows.append(row(name, run, map_chamfers(run, truth) if ok and truth else "–"))
        print(" | ".join(map(str, rows[-1])), flush=True)
    body = (
        f"`python benchmarks/scoreboard.py{' --long' if args.long else ''}` at {git_rev()}: "
        f"`mslam run SOURCE --prior twoview` (RGB only, uncalibrated unless named so, default "
        f"settings, 160x120) on the clip {args.clip.name}, its variants "
        "(`video_variants.py`, `hard_variants.py`), the synthetic paths and the clip re-rendered "
        "with exact depth (`novel_views.py --depth`, 320x240, 55°); the last rows are RGB-D "
        f"default runs. {args.jobs} runs at a time (frames per second lower than alone). Map "
        "chamfer for the runs on the clip and on its renderings (`mslam eval --map "
        "--truth-rgbd`, under the trajectory's Sim(3) and after `--map-icp`).\n\n"
        + table(HEADER, rows)
    )
    if not args.no_write and args.only is None:
        write_section("scoreboard", "Scoreboard: every input this repository makes", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
