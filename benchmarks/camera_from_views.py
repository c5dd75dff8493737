"""The camera of uncalibrated videos from many views: each stretch's estimate and the decision.

For each SOURCE, opened as ``mslam run SOURCE --prior twoview`` opens it, runs the many-view
estimate (``mslam.priors.twoview_selfcal.estimate_camera``: point tracks at 320 px, one
reconstruction and bundle adjustment per stretch, the stretches compared) and prints one row:
each stretch's focal length (a factor of the 60° guess) and radial coefficient with their
standard deviations, the decision and the seconds. ``--true SCALE,K`` (one per source, ``-``
where unknown) adds the errors against a known camera; ``--figure OUT.png`` draws every
stretch's estimate in the (focal length, radial coefficient) plane with the known cameras
(labels that share their first word share a colour)::

    python benchmarks/camera_from_views.py SOURCE ... [--label NAME ...] [--true S,K ...]
        [--figure OUT.png]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mslam.config import load_config
from mslam.priors.twoview_selfcal import CameraEstimate, estimate_camera
from mslam.system import open_source


def _sd(x: object, scale: float = 1.0, digits: int = 3) -> str:
    return "∞" if x is None else f"{scale * float(x):.{digits}f}"  # type: ignore[arg-type]


def _row(label: str, est: CameraEstimate, seconds: float, true: tuple[float, float] | None) -> str:
    cells = []
    for rec in est.stretches:
        if not rec["reconstructed"]:
            cells.append("–")
            continue
        f, k = float(rec["focal_scale"]), float(rec["k"])  # type: ignore[arg-type]
        cells.append(f"×{f:.3f} ± {_sd(rec['sd_log_focal'], 100, 1)} %, "
                     f"k {k:+.3f} ± {_sd(rec['sd_k'])}")  # fmt: skip
    used = f"×{est.focal_scale:.3f}, k {est.k:+.3f}" if est.used else "two-view estimates"
    err = "–"
    if true is not None and est.used:
        err = f"{100 * (est.focal_scale / true[0] - 1):+.1f} %, {est.k - true[1]:+.3f}"
    return f"| {label} | {' / '.join(cells) or '–'} | {used} | {err} | {seconds:.1f} |"


def _figure(
    out: Path, points: list[tuple[str, CameraEstimate, tuple[float, float] | None]]
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    groups: dict[str, str] = {}  # labels sharing their first word share a colour and an entry
    for label, est, true in points:
        group = label.split()[0]
        first = group not in groups
        colour = groups.setdefault(group, f"C{len(groups) % 10}")
        st = [r for r in est.stretches if r["reconstructed"]]
        xs = [float(r["focal_scale"]) for r in st]  # type: ignore[arg-type]
        ys = [float(r["k"]) for r in st]  # type: ignore[arg-type]
        name = group if sum(p[0].split()[0] == group for p in points) > 1 else label
        ax.plot(xs, ys, "o-" if est.used else "o:", color=colour, alpha=0.8,
                label=name if first else None)  # fmt: skip
        if true is not None:
            ax.plot(*true, "*", color=colour, ms=14, mec="k")
    ax.axvline(1.0, color="0.6", lw=0.8)
    ax.set_xlabel("focal length / 60° guess")
    ax.set_ylabel("radial coefficient k (half-diagonal units)")
    ax.set_title("each stretch's camera (dots; solid: the stretches agree), known camera (star)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sources", nargs="+")
    ap.add_argument("--label", nargs="*", default=None)
    ap.add_argument("--true", nargs="*", default=None, help="SCALE,K per source or -")
    ap.add_argument("--figure", type=Path, default=None)
    args = ap.parse_args(argv)
    labels = args.label or [Path(s).name for s in args.sources]
    trues = args.true or ["-"] * len(args.sources)
    if len(labels) != len(args.sources) or len(trues) != len(args.sources):
        print("--label and --true: one per source", file=sys.stderr)
        return 2
    cfg = load_config("twoview", [])
    print("| video | stretches: focal (× guess) ± sd, k ± sd | in use | error | s |")
    print("|---|---|---|---|---|")
    points = []
    for src, label, t in zip(args.sources, labels, trues, strict=True):
        true = None if t == "-" else tuple(float(x) for x in t.split(","))
        try:
            source = open_source(src, cfg, None, "twoview")
        except (OSError, ValueError) as exc:
            print(f"{src}: {exc}", file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        est = estimate_camera(source.sequence)
        print(_row(label, est, time.perf_counter() - t0, true), flush=True)  # type: ignore[arg-type]
        points.append((label, est, true))
    if args.figure is not None:
        _figure(args.figure, points)  # type: ignore[arg-type]
        print(args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
