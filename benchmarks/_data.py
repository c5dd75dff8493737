"""Where the benchmarks find the real data: ``--data DIR``, else ``$MSLAM_DATA``, else the default.

The data folder holds ``seq/`` (the 7-Scenes clip: redkitchen frames 0-149, RGB-D with
ground-truth poses), ``ba/`` (BAL problems) and ``traj/`` (trajectory pairs with evo's numbers).
A benchmark that needs it and does not find it skips those runs or says so in one line.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

#: The one default data folder of the benchmarks: ``shared/data`` beside the checkout.
DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: The 7-Scenes clip inside the data folder.
SEVEN_SCENES_CLIP = Path("seq") / "7scenes_redkitchen_f000000-000149"
#: BAL Ladybug-49 inside the data folder.
BAL_LADYBUG_49 = Path("ba") / "problem-49-7776-pre.txt"


def data_dir(arg: str | Path | None = None) -> Path:
    """The data folder: ``arg`` (``--data``), else ``$MSLAM_DATA``, else :data:`DEFAULT_DATA`."""
    return Path(arg or os.environ.get("MSLAM_DATA") or DEFAULT_DATA)


def seven_scenes(arg: str | Path | None = None) -> Path:
    """The 7-Scenes clip in the data folder chosen by :func:`data_dir`."""
    return data_dir(arg) / SEVEN_SCENES_CLIP


def add_data_argument(ap: argparse.ArgumentParser) -> None:
    """``--data DIR``: the data folder (default ``$MSLAM_DATA``, else shared/data beside the
    checkout)."""
    ap.add_argument(
        "--data",
        type=Path,
        default=None,
        help="data folder with seq/ ba/ traj/ (default: $MSLAM_DATA, else the shared data folder)",
    )
