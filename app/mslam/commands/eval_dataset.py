"""``mslam eval-dataset ROOT --dataset tum|7scenes|euroc|eth3d`` — score every sequence of a dataset.

::

    mslam eval-dataset ROOT --dataset NAME --out DIR [--calib] [--prior rgbd|twoview|mast3r]
                       [--config FILE] [--kernels ref|fast] [--max-frames N]
                       [--set SECTION.KEY=VALUE ...]

Upstream ships one evaluation script per dataset (``scripts/eval_tum.sh`` and friends, with and
without calibration). This is the same in one command:

1. find every sequence under ROOT in the dataset's own layout (:func:`find_sequences`): TUM and
   ETH3D folders with ``rgb.txt``/``associations.txt``, 7-Scenes folders with
   ``frame-*.color.*``, EuRoC folders with ``mav0/cam0/data.csv``;
2. run each with the packaged ``eval_no_calib.yaml`` or, with ``--calib``, ``eval_calib.yaml``
   (the dataset's own intrinsics), writing the usual run outputs into ``DIR/<sequence>/``;
   the prior is the RGB-D one where a sequence has depth. ``--prior twoview`` evaluates the
   RGB-only path instead (the paper's own setting; EuRoC has no depth, so it needs it), with
   the packaged ``twoview.yaml`` (``use_calib`` with ``--calib``); ``--prior mast3r`` the
   network (``base.yaml`` or ``calib.yaml``);
3. a sequence that fails (bad files, no depth for the default prior, ...) is reported and
   skipped; a sequence whose ``DIR/<sequence>/summary.json`` exists is not run again, so an
   interrupted evaluation resumes where it stopped;
4. a sequence with depth and ground truth also gets the dense-map metrics of paper Table 3
   (:func:`map_scores`, ``mslam.map_metrics``): the run's ``reconstruction.ply`` moved by the
   trajectory's Sim(3) against the depth of every 5th frame, and once more after ICP; stored
   in ``DIR/<sequence>/map_metrics.json``;
5. progress goes to stderr; ``DIR/results.md`` and ``DIR/results.csv`` get the table (per
   sequence: ATE RMSE and the frames it covers, map accuracy, completion, chamfer, far share
   and chamfer after ICP, frames posed, keyframes, FPS, scale, rotation gain
   (``mslam.rotation_metrics``: 1 when the estimate turns as much as the camera), warnings;
   and the mean), which
   is also printed.

Public names, in reading order:
    DATASETS, find_sequences, sequence_name, run_sequence, map_scores, results_rows,
    results_markdown, results_csv, register, run
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any

from mslam.atomic import write_atomic
from mslam.commands import UserError

__all__ = [
    "DATASETS",
    "find_sequences",
    "map_scores",
    "register",
    "results_csv",
    "results_markdown",
    "results_rows",
    "run",
    "run_sequence",
    "sequence_name",
]

#: Dataset names and the file that marks one of their sequence folders.
DATASETS = {
    "tum": "rgb.txt or associations.txt",
    "7scenes": "frame-XXXXXX.color.png/jpg",
    "euroc": "mav0/cam0/data.csv",
    "eth3d": "rgb.txt or associations.txt",
}


def find_sequences(root: str | Path, dataset: str) -> list[Path]:
    """Sequence folders under ``root`` (``root`` itself included, symlinks followed), sorted."""
    import fnmatch
    import os

    root = Path(root)
    if dataset not in DATASETS:
        raise ValueError(f"--dataset: unknown dataset {dataset!r}; choose one of {list(DATASETS)}")
    hits = set()
    for d, _dirs, files in os.walk(root, followlinks=True):
        here = Path(d)
        if dataset == "euroc":
            if here.name == "cam0" and "data.csv" in files:
                seq = here.parent
                hits.add(seq.parent if seq.name == "mav0" else seq)
        elif dataset == "7scenes":
            if any(fnmatch.fnmatch(f, "frame-*.color.*") for f in files):
                hits.add(here)
        elif "rgb.txt" in files or "associations.txt" in files:
            hits.add(here)
    return sorted(hits)


def sequence_name(root: Path, seq: Path) -> str:
    """Output folder name of a sequence: its path below ROOT with ``/`` → ``_``."""
    import os

    rel = Path(os.path.relpath(seq, root))
    return "_".join(rel.parts) if rel.parts and rel.parts != (".",) else seq.resolve().name


def run_sequence(
    path: Path, cfg: Any, kernels: Any, out: Path, max_frames: int | None, prior: str | None = None
) -> dict:
    """One sequence through the system with ``prior`` (None: the source's default); writes the
    run outputs, returns the summary."""
    from mslam.config import config_to_dict
    from mslam.system import open_source, run_slam, write_outputs

    source = open_source(str(path), cfg, None, prior, max_frames)
    system, meta = run_slam(source, cfg, kernels, progress=False)
    if meta["interrupted"]:
        raise KeyboardInterrupt  # no summary.json: a resumed evaluation runs it again
    meta["config"] = config_to_dict(cfg)
    return write_outputs(out, system, source.sequence, meta)


def map_scores(path: Path, out: Path) -> dict[str, Any]:
    """Dense-map metrics of the run in ``out`` against the RGB-D sequence at ``path``.

    Returns:
        ``accuracy_m``, ``completion_m``, ``chamfer_m``, ``far`` (trajectory Sim(3) alignment)
        and ``chamfer_icp_m`` (after ICP); read from ``out/map_metrics.json`` when present,
        else computed and written there.

    Raises:
        ValueError / OSError: no depth or ground truth, or unreadable run outputs.
    """
    from mslam import formats as io
    from mslam.datasets import load_sequence
    from mslam.map_metrics import evaluate_map, truth_from_rgbd

    done = out / "map_metrics.json"
    if done.is_file():
        return json.loads(done.read_text())
    seq = load_sequence(path)
    gt = seq.ground_truth()
    if gt is None:
        raise ValueError(f"{path}: no ground-truth pose for any frame")
    ts, T = io.read_tum(out / "trajectory.txt")
    xyz = io.read_ply(out / "reconstruction.ply")[0]
    truth = truth_from_rgbd(seq, t_range=(float(ts.min()) - 0.01, float(ts.max()) + 0.01))
    m, _, _ = evaluate_map(xyz, ts, T, gt[1], gt[2], truth)
    m_icp, _, _ = evaluate_map(xyz, ts, T, gt[1], gt[2], truth, refine="icp")
    res = {
        "accuracy_m": m.accuracy,
        "completion_m": m.completion,
        "chamfer_m": m.chamfer,
        "far": m.far,
        "chamfer_icp_m": m_icp.chamfer,
    }
    write_atomic(done, json.dumps(res, indent=2) + "\n")
    return res


#: The map columns of the table (:func:`map_scores`).
MAP_KEYS = ("accuracy_m", "completion_m", "chamfer_m", "far", "chamfer_icp_m")


def results_rows(results: list[tuple[str, dict | None, str]]) -> list[dict[str, Any]]:
    """Table rows from ``(name, summary or None, status)``; the mean row last."""
    rows = []
    for name, s, status in results:
        r: dict[str, Any] = {"sequence": name, "status": status}
        if s is not None:
            r.update(
                ate_rmse_m=s.get("ate_rmse"),
                ate_frames=s.get("ate_frames"),
                frames_posed=s["frames_with_pose"],
                frames=s["frames"],
                keyframes=s["keyframes"],
                fps=s.get("frames_per_second"),
                scale=(s.get("ate") or {}).get("scale"),
                rotation_gain=(s.get("rotation") or {}).get("rotation_gain"),
                warnings=len(s.get("warnings", [])),
                cautions=len(s.get("cautions", [])),
            )
            r.update((k, (s.get("map") or {}).get(k)) for k in MAP_KEYS)
        rows.append(r)
    ok = [r for r in rows if r.get("ate_rmse_m") is not None]
    mean: dict[str, Any] = {"sequence": "mean", "status": f"{len(ok)} of {len(rows)} scored"}
    for key in ("ate_rmse_m", "fps", "rotation_gain", *MAP_KEYS):
        vals = [r[key] for r in ok if r.get(key) is not None]
        mean[key] = sum(vals) / len(vals) if vals else None
    return [*rows, mean]


COLUMNS = ("sequence", "ate_rmse_m", "ate_frames", *MAP_KEYS, "frames_posed", "frames",
           "keyframes", "fps", "scale", "rotation_gain", "warnings", "cautions", "status")  # fmt: skip


def _fmt(v: Any, key: str) -> str:
    if v is None:
        return ""
    if key == "ate_rmse_m" or key in MAP_KEYS:
        return f"{v:.4f}"
    if key in ("fps", "scale", "rotation_gain"):
        return f"{v:.2f}" if key == "fps" else f"{v:.3f}"
    return str(v)


def results_markdown(rows: list[dict[str, Any]], title: str) -> str:
    """The paper's form (one row, ATE per sequence and the mean) and the detail table."""
    seqs = rows[:-1]
    head = ["method", *[r["sequence"] for r in seqs], "avg"]
    vals = ["mslam", *[_fmt(r.get("ate_rmse_m"), "ate_rmse_m") or "fail" for r in seqs]]
    vals.append(_fmt(rows[-1].get("ate_rmse_m"), "ate_rmse_m"))
    lines = [f"## {title}", "", "ATE RMSE [m] (Sim(3) alignment, evo's association):", ""]
    lines += [
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
        "| " + " | ".join(vals) + " |",
    ]
    if any(r.get("chamfer_m") is not None for r in seqs):
        lines += ["", "Map chamfer [m] (trajectory Sim(3) / after ICP; mslam.map_metrics):", ""]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for key in ("chamfer_m", "chamfer_icp_m"):
            cells = [_fmt(r.get(key), key) or "-" for r in seqs]
            avg = _fmt(rows[-1].get(key), key)
            lines.append("| " + " | ".join([f"mslam ({key})", *cells, avg]) + " |")
    lines += ["", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(k), k) for k in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def results_csv(rows: list[dict[str, Any]]) -> str:
    """The detail table as CSV (header: :data:`COLUMNS`)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k) for k in COLUMNS})
    return buf.getvalue()


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``eval-dataset`` sub-command."""
    p = subparsers.add_parser(
        "eval-dataset",
        help="run and score every sequence of a dataset (results table)",
        description="Find every sequence of --dataset under ROOT, run each with the packaged "
        "eval config (eval_no_calib.yaml, or eval_calib.yaml with --calib), skip and report "
        "failures, resume finished ones, and write DIR/results.md and DIR/results.csv.",
    )
    p.add_argument("root", type=Path, metavar="ROOT", help="dataset root folder")
    p.add_argument("--dataset", required=True, choices=tuple(DATASETS), help="dataset layout")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--calib", action="store_true", help="calibrated mode (dataset intrinsics)")
    p.add_argument(
        "--prior",
        choices=("rgbd", "twoview", "mast3r"),
        help="where pointmaps come from (default: rgbd for sequences with depth; twoview: RGB "
        "only, the packaged twoview.yaml)",
    )
    p.add_argument("--config", metavar="FILE", help="config instead of the packaged eval one")
    p.add_argument("--kernels", choices=("ref", "fast"), default="fast", help="kernel set")
    p.add_argument("--max-frames", type=int, metavar="N", help="at most N frames per sequence")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Handler of ``mslam eval-dataset``; returns 0 when at least one sequence was scored."""
    from mslam.config import load_config
    from mslam.kernels import load_kernels

    if not args.root.is_dir():
        raise UserError(f"{args.root}: no such folder")
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f"--max-frames: must be >= 1, got {args.max_frames}")
    seqs = find_sequences(args.root, args.dataset)
    if not seqs:
        raise UserError(
            f"{args.root}: no {args.dataset} sequence found (looked for {DATASETS[args.dataset]})"
        )
    cfg = load_config(*_config(args))
    kernels = load_kernels(args.kernels)
    results = []
    for k, seq in enumerate(seqs, 1):
        name = sequence_name(args.root, seq)
        results.append(_one(k, len(seqs), name, seq, cfg, kernels, args))
    rows = results_rows(results)
    mode = "calibrated" if args.calib else "uncalibrated"
    title = (
        f"{args.dataset} ({mode}{f', {args.prior} prior' if args.prior else ''}), {args.kernels}"
    )
    md = results_markdown(rows, title)
    write_atomic(args.out / "results.md", md)
    write_atomic(args.out / "results.csv", results_csv(rows))
    print(md)
    return 0 if any(s is not None for _, s, _ in results) else 1


def _config(args: argparse.Namespace) -> tuple[str, list[str]]:
    """The config to load and its overrides: ``--config``, else the packaged eval config of
    the prior (module docstring, step 2)."""
    keys = list(args.overrides)
    if args.config:
        return args.config, keys
    if args.prior == "twoview":
        return "twoview", [*(["use_calib=true"] if args.calib else []), "single_thread=true", *keys]
    if args.prior == "mast3r":
        return ("calib" if args.calib else "base"), ["single_thread=true", *keys]
    return ("eval_calib" if args.calib else "eval_no_calib"), keys


def _one(k: int, n: int, name: str, seq: Path, cfg: Any, kernels: Any, args: Any):
    out = args.out / name
    done = out / "summary.json"
    if done.is_file():
        print(f"[{k}/{n}] {name}: done before, reusing {done}", file=sys.stderr)
        s = json.loads(done.read_text())
        return name, dict(s, map=_map_or_none(k, n, name, seq, out)), "resumed"
    print(f"[{k}/{n}] {name}: running", file=sys.stderr, flush=True)
    try:
        s = run_sequence(seq, cfg, kernels, out, args.max_frames, args.prior)
    except (OSError, ValueError, RuntimeError) as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        print(f"[{k}/{n}] {name}: FAILED, skipped: {msg}", file=sys.stderr)
        return name, None, f"failed: {msg}"
    s = dict(s, map=_map_or_none(k, n, name, seq, out))
    ate = f"ATE {s['ate_rmse']:.4f} m, " if s.get("ate_rmse") is not None else ""
    if s["map"] is not None:
        ate += f"map chamfer {s['map']['chamfer_m']:.4f} m, "
    print(
        f"[{k}/{n}] {name}: {ate}{s['frames_with_pose']}/{s['frames']} posed, "
        f"{s['frames_per_second'] or 0:.2f} FPS{'' if s['plausible'] else ', WARNING'}"
        f"{', caution' if s.get('cautions') else ''}",
        file=sys.stderr,
    )
    return name, s, "ok"


def _map_or_none(k: int, n: int, name: str, seq: Path, out: Path) -> dict | None:
    """:func:`map_scores`, or None (reported on stderr) when the sequence cannot be scored."""
    try:
        return map_scores(seq, out)
    except (OSError, ValueError) as exc:
        print(f"[{k}/{n}] {name}: no map metrics: {exc}", file=sys.stderr)
        return None
