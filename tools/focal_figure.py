"""The focal-length cost of videos, side by side (the figure in docs/priors.md).

::

    python tools/focal_figure.py OUT.png SOURCE [SOURCE ...] [--label NAME ...] [--true PX ...]

For each ``SOURCE`` (as ``mslam run`` takes it, opened with the two-view configuration) the
pairs' self-calibration costs of ``mslam.priors.twoview_focal`` are summed and drawn against the
focal length (as a factor of the 60° guess), normalised to [0, 1], with the bootstrap's 10–90 %
range of the estimate shaded, the band ``[guess, LONG_BIAS · guess]`` hatched, and the true
focal length (``--true``, pixels at the working resolution) dashed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("sources", nargs="+")
    ap.add_argument("--label", nargs="*", default=None)
    ap.add_argument("--true", nargs="*", type=float, default=None)
    args = ap.parse_args(argv)
    labels = args.label or args.sources
    truths = args.true or [float("nan")] * len(args.sources)
    if len(labels) != len(args.sources) or len(truths) != len(args.sources):
        print("--label / --true: one per SOURCE", file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    import numpy as np

    from mslam.config import load_config
    from mslam.priors.twoview_focal import LONG_BIAS, SEARCH, decide, pair_costs
    from mslam.system import open_source

    fig, axes = plt.subplots(1, len(args.sources), figsize=(3.2 * len(args.sources), 2.8))
    for ax, source, label, f_true in zip(np.atleast_1d(axes), args.sources, labels, truths):
        src = open_source(source, load_config("twoview", []), None, "twoview")
        costs, guess = pair_costs(src.sequence)
        est = decide(costs, guess)
        total = costs.sum(0) if len(costs) else np.zeros(len(SEARCH))
        span = max(float(np.ptp(total)), 1e-12)
        ax.plot(SEARCH, (total - total.min()) / span, color="C0")
        ax.axvspan(1.0, LONG_BIAS, color="0.85", hatch="//", lw=0)
        if est.low_px is not None and est.high_px is not None:
            ax.axvspan(est.low_px / guess, est.high_px / guess, color="C0", alpha=0.25)
        if np.isfinite(f_true):
            ax.axvline(f_true / guess, color="k", ls="--", lw=1)
        ax.set_xscale("log")
        ax.set_xticks([0.5, 0.7, 1, 1.4, 2], ["0.5", "0.7", "1", "1.4", "2"])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(f"{label}\n{'used' if est.used else 'guess kept'}, {est.pairs} pairs",
                     fontsize=9)  # fmt: skip
        ax.set_xlabel("focal length / 60° guess", fontsize=8)
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
