"""The lens-distortion residual of videos, side by side (the figure in docs/priors.md).

::

    python tools/lens_figure.py OUT.png SOURCE [SOURCE ...] [--label NAME ...]

For each ``SOURCE`` (as ``mslam run`` takes it, opened with the two-view configuration) the
pairs of the focal pre-pass (``mslam.priors.twoview_focal``) give their residual curves over
the division coefficient (``mslam.priors.twoview_lens.residual_curve``); each curve is divided
by its minimum and the curves are averaged. The figure draws that mean against ``λ`` with the
bootstrap's 10–90 % range shaded, and the line ``MIN_GAIN`` times the minimum, which the
pinhole (``λ = 0``) must exceed for the lens to be used. Above it, a frame of the video.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _curves(sequence):  # (P, len(LAMBDAS)) residual curves of the pre-pass's pairs
    import numpy as np

    from mslam.priors import twoview_focal as tf
    from mslam.priors.twoview_geometry import focal_guess_intrinsics
    from mslam.priors.twoview_lens import LAMBDAS

    H, W = sequence[0].shape
    K = focal_guess_intrinsics(W, H)
    out = []
    for i, j in tf.pair_indices(len(sequence)):
        found = tf.pair_samples(sequence[i].rgb, sequence[j].rgb, K, i)
        curve = None if found is None else tf.lens_curve(*found, W, H)
        if curve is not None:
            out.append(curve)
    return np.asarray(out).reshape(-1, len(LAMBDAS))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("sources", nargs="+")
    ap.add_argument("--label", nargs="*", default=None)
    args = ap.parse_args(argv)
    labels = args.label or args.sources
    if len(labels) != len(args.sources):
        print("--label: one per SOURCE", file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mslam.config import load_config
    from mslam.priors.twoview_lens import LAMBDAS, MIN_GAIN, decide_lens
    from mslam.system import open_source

    k = len(args.sources)
    fig, axes = plt.subplots(2, k, figsize=(2.9 * k, 4.6), height_ratios=[1, 1.2], squeeze=False)
    for col, (source, label) in enumerate(zip(args.sources, labels)):
        seq = open_source(source, load_config("twoview", []), None, "twoview").sequence
        axes[0, col].imshow(seq[len(seq) // 2].rgb)
        axes[0, col].set_axis_off()
        axes[0, col].set_title(label, fontsize=9)
        curves = _curves(seq)
        est = decide_lens(curves)
        ax = axes[1, col]
        if len(curves):
            mean = (curves / curves.min(1, keepdims=True)).mean(0)
            ax.plot(LAMBDAS, mean, color="C0")
            ax.axhline(MIN_GAIN * mean.min(), color="0.5", ls=":", lw=1)
        if est.low is not None and est.high is not None:
            ax.axvspan(est.low - 0.005, est.high + 0.005, color="C0", alpha=0.25)
        ax.axvline(0.0, color="k", lw=0.6)
        verdict = f"λ {est.lam:+.3f} used" if est.used else "pinhole kept"
        ax.set_title(f"{verdict}, {est.pairs} pairs", fontsize=8)
        ax.set_xlabel("division coefficient λ", fontsize=8)
        ax.tick_params(labelsize=7)
        if col == 0:
            ax.set_ylabel("residual / pair's best", fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
