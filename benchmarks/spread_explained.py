"""Can the map itself tell a drifting scale from a scene at another distance?

The spread watch (``mslam.system.divergence_checks.map_spread``) reads the scene's distance in
world units, ``d_k = s_k · median |X_canon_k|``, over the last 8 keyframes and takes out the
part that the keyframes' motion along their optical axes explains. A camera that turns
towards farther surfaces, or sinks towards the floor, changes ``d_k`` as a drifting scale
does. This script measures, after every new keyframe of a run (the poses and pointmaps of
that moment, as the watch reads them), two things the map itself offers:

* **link consistency**: for each consecutive-keyframe edge ``(i, j)``, the median over its
  matched pixels of ``log(|P_j - c_j| / |P_i - c_j|)``, a point's distance from camera ``j``
  through ``j``'s own pointmap and through ``i``'s (both in world units). A scale that jumped
  between the two keyframes shows here: the backend weighs a point's distance along its ray
  far less than the ray's direction (``sigma_dist`` 10 against ``sigma_ray`` 0.003), so a
  pointmap scaled about its camera, which keeps its rays, is hardly corrected.
* **the map's prediction**: the change of ``d_k`` left after replacing the motion model by
  the previous keyframe's points seen from the new camera (those inside its field of view,
  taken from the new keyframe's own pointmap): ``log(d_k / median |P_{k-1} - c_k|)``.

For every window of 8 consecutive keyframes it prints the factor by which ``d_k`` moved
(``own``), what is left after the optical-axis correction (``axis``, the watch's figure) and
after the map's prediction (``map``), and the product of the window's link ratios
(``links``); per run the largest of each, and of ``both``: the smaller of ``axis`` and
``links`` where the two move the same way. Findings: benchmarks/RESULTS.md, "Can the map
tell drift from a farther scene?".

Usage: ``python benchmarks/spread_explained.py SOURCE [--set KEY=VALUE ...] [--max-frames N]
[--calib FILE] [--windows]`` (RGB only, ``--prior twoview``); prints, writes nothing.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from mslam.config import load_config
from mslam.datasets.frame import Frame
from mslam.kernels import load_kernels
from mslam.system import SlamSystem, open_source, run_slam
from mslam.system.divergence_checks import explained_log_changes
from mslam.system.state import FrameStatus
from mslam_ref import sim3, so3

#: Keyframes per window, as the watch's ``spread_window``.
WINDOW = 8
#: Share of the new keyframe's own view directions (per axis, both ends) that bounds its field
#: of view: the 2nd to the 98th percentile of ``x/z`` and ``y/z``.
FOV_PERCENTILES = (2.0, 98.0)
#: Fewer of the previous keyframe's points in view and the map predicts nothing (no change).
MIN_IN_VIEW = 50


def median_distances(X: list[np.ndarray]) -> np.ndarray:
    """(K,) median distance of each pointmap's points (K of (N, 3)) to its camera."""
    return np.array([np.median(np.linalg.norm(P, axis=1)) for P in X])


def predicted_log_change(T: np.ndarray, X: list[np.ndarray], d: np.ndarray) -> np.ndarray:
    """(K-1,) log change of ``d`` that the previous keyframe's points seen from the new camera
    predict, per link (0 where fewer than ``MIN_IN_VIEW`` of them are in its view)."""
    out = np.zeros(len(T) - 1)
    for b in range(1, len(T)):
        Xb = X[b][X[b][:, 2] > 0]
        u_lim = np.percentile(Xb[:, 0] / Xb[:, 2], FOV_PERCENTILES)
        v_lim = np.percentile(Xb[:, 1] / Xb[:, 2], FOV_PERCENTILES)
        V = so3.act(so3.conj(T[b, 3:7]), sim3.act(T[b - 1], X[b - 1]) - T[b, :3])
        z = np.where(V[:, 2] > 0, V[:, 2], np.inf)
        u, v = V[:, 0] / z, V[:, 1] / z
        seen = (V[:, 2] > 0) & (u > u_lim[0]) & (u < u_lim[1]) & (v > v_lim[0]) & (v < v_lim[1])
        if seen.sum() >= MIN_IN_VIEW:
            out[b - 1] = np.log(np.median(np.linalg.norm(V[seen], axis=1)) / d[b - 1])
    return out


def link_consistency(system: SlamSystem, j: int) -> float:
    """The median log distance ratio (module docstring) of the consecutive edge into keyframe
    ``j``, over the pixels of ``j``; NaN without one."""
    kf, T = system.keyframes, system.keyframes.poses()
    for e in system.graph.edges:
        ok = np.asarray(e.valid_match_j, bool).reshape(-1)
        if e.kind != "consecutive" or e.j != j or ok.sum() < MIN_IN_VIEW:
            continue
        X_i, X_j = (np.asarray(kf[k].state.X_canon, np.float64).reshape(-1, 3) for k in (e.i, j))
        P_j = sim3.act(T[j], X_j[ok])
        P_i = sim3.act(T[e.i], X_i[np.asarray(e.idx_i2j).reshape(-1)[ok]])
        ratio = np.linalg.norm(P_j - T[j, :3], axis=1) / np.linalg.norm(P_i - T[j, :3], axis=1)
        return float(np.median(np.log(ratio)))
    return float("nan")


class Watch:
    """A frame observer (``run_slam``) that measures the newest window after every new
    keyframe, with the poses and pointmaps of that moment, as the spread watch does."""

    def __init__(self) -> None:
        self.rows: list[tuple[int, float, float, float, float, float]] = []
        self.links: list[float] = []  # per new keyframe of the current map with a link
        self.seen = 0
        self.start = 0

    def after_frame(self, i: int, frame: Frame, system: SlamSystem, status: FrameStatus) -> None:
        kf = system.keyframes
        if len(kf) == self.seen:
            return
        self.seen = len(kf)
        start = system.backend.map_start
        if start != self.start:  # a new map: its links start afresh
            self.links, self.start = [], start
        link = link_consistency(system, len(kf) - 1) if len(kf) - start >= 2 else float("nan")
        if not np.isnan(link):
            self.links.append(link)
        if len(kf) - start <= WINDOW:
            return
        ks = range(len(kf) - WINDOW - 1, len(kf))
        T = kf.poses()[ks.start :]
        X = [np.asarray(kf[k].state.X_canon, np.float64).reshape(-1, 3) for k in ks]
        m = median_distances(X)
        d = T[:, 7] * m  # the scene's distance in world units
        o = float(np.log(d[-1] / d[0]))
        explained = float(np.sum(explained_log_changes(T, m)))
        ax = float(np.clip(explained, min(o, 0), max(o, 0)))  # as map_spread
        p = o - float(predicted_log_change(T, X, d).sum())
        net = float(np.sum(self.links[-WINDOW:]))
        self.rows.append(
            (int(frame.index), np.exp(o), np.exp(o - ax), np.exp(p), link, np.exp(net))
        )


def far(f: float) -> float:
    """A factor's distance from 1, as the larger of it and its inverse."""
    return max(f, 1 / f)


def agree(a: float, b: float) -> float:
    """Two factors' agreement: the smaller distance from 1 (:func:`far`) when both move the
    same way, else 1."""
    return min(far(a), far(b)) if (a > 1) == (b > 1) else 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--calib", default=None, help="intrinsics YAML (calibrated run)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--windows", action="store_true", help="print every window")
    a = ap.parse_args()
    cfg = load_config("twoview", a.set)
    src = open_source(a.source, cfg, a.calib, "twoview", a.max_frames)
    if a.calib is not None:
        cfg = replace(cfg, use_calib=True)
    watch = Watch()
    system, _ = run_slam(src, cfg, load_kernels("fast"), observer=watch)
    for f, o, ax, p, link, net in watch.rows if a.windows else []:
        print(
            f"frame {f:4d}: own x{o:6.2f}  after axis x{ax:6.2f}  after map x{p:6.2f}  "
            f"link {link:+.3f}  links x{net:6.2f}"
        )
    cols = np.array([[far(r[1]), far(r[2]), far(r[3]), far(r[5]), agree(r[2], r[5])]
                     for r in watch.rows])  # fmt: skip
    worst = cols.max(axis=0) if len(cols) else np.full(5, np.nan)
    links = np.abs(watch.links)
    spread = [e for e in system.divergence.events if e["kind"] == "spread"]
    print(
        f"{a.source}: {len(system.keyframes)} keyframes; worst window: own {worst[0]:.2f}, "
        f"after axis {worst[1]:.2f}, after map {worst[2]:.2f}, links {worst[3]:.2f}, both {worst[4]:.2f}; links' "
        f"|median log ratio| median {np.median(links) if len(links) else np.nan:.3f}, max "
        f"{links.max() if len(links) else np.nan:.3f}; the watch: "
        f"{spread[0]['frame'] if spread else 'silent'}"
    )


if __name__ == "__main__":
    main()
