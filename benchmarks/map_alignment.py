"""How well can the trajectory's Sim(3) place a map on a given clip? A perfect-map experiment.

The dense-map metrics of the paper's 7-Scenes table (§4.2) move the map by the Sim(3) that
aligns the estimated camera *positions* to the ground truth (Umeyama). That fit fixes the
rotation about an axis only through the positions' spread across it. This script takes the
clip's ground-truth path, adds position errors of a chosen ATE, fits the Sim(3) as the
evaluation does, and moves the **true** cloud with it: the chamfer distance that results is
what a perfect map would score with such a trajectory. Two error shapes bracket real ones:

* ``white`` — independent per-frame errors (jitter);
* ``walk`` — a random walk (drift), the shape of a SLAM trajectory's error.

Each error is rescaled so its aligned RMSE equals the ATE of the row.

Usage: ``python benchmarks/map_alignment.py [--clip FOLDER] [--trials 20] [--ate 0.5 1 1.6]``
(ATE in cm); writes the section ``map-alignment`` of RESULTS.md unless ``--no-write``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _results import git_rev, table, write_section

from mslam.datasets import load_sequence
from mslam.evaluate import umeyama
from mslam.map_metrics import align_points, map_metrics, truth_from_rgbd

CLIP = Path(__file__).resolve().parents[2] / "shared/data/seq/7scenes_redkitchen_f000000-000149"

#: Columns of the RESULTS table.
HEADER = ["error shape", "ATE [cm]", "rotation error [°]", "p90 [°]", "chamfer [cm]", "p90 [cm]"]

#: Points drawn each way for one chamfer (the metric's full 200k changes the means < 0.1 mm).
DRAW = 20_000


def path_spread(P: np.ndarray) -> np.ndarray:
    """(3,) RMS spread (m) of (n, 3) positions along their principal axes, largest first."""
    c = P - P.mean(axis=0)
    return np.linalg.svd(c, compute_uv=False) / np.sqrt(len(P))


def error_of_ate(P: np.ndarray, shape: str, ate: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) position errors of ``shape`` ("white" or "walk") whose aligned RMSE is ``ate``."""
    e = rng.normal(size=P.shape)
    if shape == "walk":
        e = np.cumsum(e, axis=0)
        e -= e.mean(axis=0)
    for _ in range(4):  # the aligned RMSE is nearly linear in the error's size
        R, t, s = umeyama(P + e, P)
        r = s * (P + e) @ R.T + t - P
        e *= ate / np.sqrt(np.mean(np.sum(r**2, axis=1)))
    return e


def rotation_deg(R: np.ndarray) -> float:
    """Angle (degrees) of a rotation matrix."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def trial(
    P: np.ndarray, truth: np.ndarray, shape: str, ate: float, seed: int
) -> tuple[float, float]:
    """(rotation error in degrees, chamfer in m) of the perfect map under one noisy trajectory."""
    rng = np.random.default_rng(seed)
    R, t, s = umeyama(P + error_of_ate(P, shape, ate, rng), P)
    moved = align_points(truth, R, t, s)
    return rotation_deg(R), map_metrics(moved, truth, max_points=DRAW, seed=seed).chamfer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", type=Path, default=CLIP)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--ate", type=float, nargs="+", default=[0.5, 1.0, 1.6, 2.7], help="cm")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    seq = load_sequence(args.clip)
    P = np.asarray(seq.T_WC)[:, :3]
    truth = truth_from_rgbd(seq)
    spread = path_spread(P)
    rows = []
    for shape in ("white", "walk"):
        for ate_cm in args.ate:
            res = np.array([trial(P, truth, shape, ate_cm / 100, k) for k in range(args.trials)])
            ang, ch = res[:, 0], 100 * res[:, 1]
            rows.append([shape, f"{ate_cm:.1f}", f"{np.median(ang):.2f}", f"{np.percentile(ang, 90):.2f}",
                         f"{np.median(ch):.2f}", f"{np.percentile(ch, 90):.2f}"])  # fmt: skip
            print(*rows[-1], flush=True)
    body = (
        f"`python benchmarks/map_alignment.py --trials {args.trials}` at {git_rev()}, "
        f"{args.clip.name}: {len(P)} ground-truth positions whose RMS spread along their principal "
        f"axes is {spread[0] * 100:.1f} / {spread[1] * 100:.1f} / {spread[2] * 100:.1f} cm, "
        f"{len(truth):,} truth points. The **true** cloud, moved by the Sim(3) that aligns a "
        "noisy copy of the true path to the true path: the chamfer a perfect map scores under the "
        f"trajectory alignment. Medians and 90th percentiles over {args.trials} draws.\n\n"
        + table(HEADER, rows)
    )
    if not args.no_write:
        write_section("map-alignment", "How well the trajectory's Sim(3) places a map", body)
    print(body)


if __name__ == "__main__":
    main()
