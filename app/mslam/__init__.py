"""mslam — the application: run MASt3R-SLAM on a sequence, score it, adjust bundles.

This package is the top layer of three (``mslam`` → ``mslam_fast`` → ``mslam_ref``): the
``mslam`` command and its sub-commands, configurations, the kernel set, datasets and loaders,
the pointmap priors, the SLAM system (frontend, graph, relocalisation, backend step),
outputs and evaluation. The maths lives in ``mslam_ref`` (NumPy/SciPy) and its Taichi twins
in ``mslam_fast``; everything that needs OpenCV, YAML, tqdm, matplotlib or torch lives here.

Quick use (the same as ``mslam run synthetic:loop:40:96x72 --out runs/x``)::

    import mslam

    result = mslam.run("synthetic:loop:40:96x72", out="runs/x")
    result.summary["ate_rmse"]

The pieces one by one (what ``mslam.run`` does inside)::

    cfg = mslam.load_config()
    source = mslam.open_source("synthetic:loop:40:96x72", cfg)
    system, meta = mslam.run_slam(source, cfg, mslam.load_kernels("fast"))
    mslam.write_outputs("runs/x", system, source.sequence, meta)

Public names: run, RunResult, load_config, load_kernels, open_source, run_slam, write_outputs.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"

__all__ = [
    "RunResult",
    "load_config",
    "load_kernels",
    "open_source",
    "run",
    "run_slam",
    "write_outputs",
]

_LAZY = {
    "run": "mslam.api",
    "RunResult": "mslam.api",
    "load_config": "mslam.config",
    "load_kernels": "mslam.kernels",
    "open_source": "mslam.system",
    "run_slam": "mslam.system",
    "write_outputs": "mslam.system",
}


def __getattr__(name: str) -> Any:
    """Import the public names on first use, so ``import mslam`` stays light."""
    if name not in _LAZY:
        raise AttributeError(f"module 'mslam' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(_LAZY[name]), name)
