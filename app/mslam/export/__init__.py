"""Looking inside a run: a Rerun recording, a COLMAP model, per-frame depth maps (docs/outputs.md).

Modules, in reading order:

* :mod:`~mslam.export.observer` — the narrow :class:`RunObserver` interface and the
  :class:`SystemTap` that the SLAM loop calls once per frame;
* :mod:`~mslam.export.rerun_log` — :class:`RerunRecorder`, a ``RunObserver`` writing ``.rrd``;
* :mod:`~mslam.export.camera` — the intrinsics the exports use (given or estimated);
* :mod:`~mslam.export.colmap` — the final map as a COLMAP model (text and binary);
* :mod:`~mslam.export.depth` — depth maps of every posed frame from its keyframe's pointmap;
* :mod:`~mslam.export.request` — ``mslam run``'s options, written inside the one output set.

Public names, in reading order:
    RunObserver, SystemTap, RerunRecorder, run_intrinsics, write_colmap, write_depth_maps,
    ExportRequest
"""

from __future__ import annotations

from mslam.export.camera import run_intrinsics
from mslam.export.colmap import write_colmap
from mslam.export.depth import write_depth_maps
from mslam.export.observer import RunObserver, SystemTap
from mslam.export.request import ExportRequest

__all__ = [
    "ExportRequest",
    "RerunRecorder",
    "RunObserver",
    "SystemTap",
    "run_intrinsics",
    "write_colmap",
    "write_depth_maps",
]


def __getattr__(name: str):
    if name == "RerunRecorder":  # imported on use: rerun-sdk is an optional extra
        from mslam.export.rerun_log import RerunRecorder

        return RerunRecorder
    raise AttributeError(name)
