"""Top-down and side views of runs' maps over the true surface (the figures in docs/evaluation.md).

::

    python tools/map_figure.py CLIP OUT.png RUN [RUN ...] [--label NAME ...] [--icp | --both]

Each ``RUN`` folder holds ``trajectory.txt`` and ``reconstruction.ply``. The map is moved by the
Sim(3) that aligns the trajectory to the clip's ground truth (``mslam.map_metrics``; with
``--icp`` then registered rigidly onto the truth; ``--both``: a row for each) and drawn, one
row per run and alignment, from the top (x–y
of the truth's world frame after removing its vertical principal axis) and from the side, in
colour over the truth cloud (grey). Points are subsampled so the PNG stays small.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

#: Points drawn per cloud (a seeded draw): enough to see the surfaces, about 65 KB of PNG per
#: row.
DRAW_POINTS = 12_000


def _aligned(seq: Any, run: Path, truth: np.ndarray, icps: list[bool]) -> list[np.ndarray]:
    """The run's map moved by the trajectory's Sim(3) to the clip ``seq``'s ground truth, then
    (for each ``True`` in ``icps``) registered onto ``truth``: one cloud per entry."""
    from mslam.evaluate import ate
    from mslam.formats import read_ply, read_trajectory
    from mslam.map_metrics import align_points, icp_refine

    ts, T = read_trajectory(run / "trajectory.txt")
    xyz, _ = read_ply(run / "reconstruction.ply")
    res = ate(ts, T, np.asarray(seq.timestamps, float), np.asarray(seq.T_WC), "sim3")
    R, t, s = res.rotation, res.translation, res.scale
    return [align_points(xyz, *(icp_refine(xyz, truth, R, t, s) if icp else (R, t, s)))
            for icp in icps]  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clip", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--label", nargs="*", default=None)
    how = ap.add_mutually_exclusive_group()
    how.add_argument("--icp", action="store_true")
    how.add_argument("--both", action="store_true", help="trajectory Sim(3), then ICP")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mslam.datasets import load_sequence
    from mslam.map_metrics import truth_from_rgbd

    seq = load_sequence(str(args.clip))
    truth = truth_from_rgbd(seq)
    # Axes of the drawing: the truth's principal axes, the least spread one as "up".
    mu = truth.mean(0)
    _, _, Vt = np.linalg.svd(truth - mu, full_matrices=False)
    rng = np.random.default_rng(0)

    def frame(P: np.ndarray) -> np.ndarray:
        P = P[rng.choice(len(P), min(len(P), DRAW_POINTS), replace=False)]
        return (P - mu) @ Vt.T

    tr = frame(truth)
    labels = args.label or [r.name for r in args.runs]
    modes = [(False, "trajectory Sim(3)"), (True, "ICP")] if args.both else [(args.icp, "")]
    icps = [icp for icp, _ in modes]
    rows = [(f"{name}, {how}" if how else name, cloud)
            for run, name in zip(args.runs, labels, strict=True)
            for (_, how), cloud in zip(modes, _aligned(seq, run, truth, icps))]  # fmt: skip
    fig, axes = plt.subplots(len(rows), 2, figsize=(8, 3.2 * len(rows)), squeeze=False)
    for row, (name, cloud) in enumerate(rows):
        M = frame(cloud)
        for col, (a, b, view) in enumerate(((0, 1, "top-down"), (0, 2, "side"))):
            ax = axes[row, col]
            ax.scatter(tr[:, a], tr[:, b], s=0.2, c="0.7", lw=0, rasterized=True)
            ax.scatter(M[:, a], M[:, b], s=0.2, c="tab:red", lw=0, rasterized=True)
            ax.set_aspect("equal")
            ax.set_xlim(tr[:, a].min() - 0.3, tr[:, a].max() + 0.3)
            ax.set_ylim(tr[:, b].min() - 0.3, tr[:, b].max() + 0.3)
            ax.set_title(f"{name}: {view}", fontsize=9)
            ax.tick_params(labelsize=7)
            ax.set_xlabel("m", fontsize=7)
    fig.suptitle("map (red) over the true surface (grey)", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=72)


if __name__ == "__main__":
    main()
