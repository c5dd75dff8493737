"""Paper §3 (docs/upstream.md §1) — the SLAM system end to end, single process and deterministic.

Upstream runs a frontend process (tracking), a backend process (graph and global
optimisation, relocalisation) and a viewer, talking through shared memory. Here everything is
one process and, by default, the backend runs synchronously after every new keyframe and every
relocalisation — upstream's ``single_thread`` evaluation mode — so a run is a pure function of
its input, config and kernel set. ``single_thread: False`` moves the backend into a
background thread (:mod:`~mslam.system.worker`), as upstream's separate process.

Modules, in reading order:

* :mod:`~mslam.system.sources` — SOURCE → frames, calibration, prior (checked up front);
* :mod:`~mslam.system.run` — :func:`run_slam`, the frame loop;
* :mod:`~mslam.system.frontend` — :class:`SlamSystem`: the mode machine, keyframe decisions;
  :mod:`~mslam.system.parallax` — its steps for the two-view prior (the parallax wait, pairs
  without parallax posed by rotation);
* :mod:`~mslam.system.tracker` — :class:`~mslam.system.tracker.Tracker`: matching, the pose
  solve, fusion and the new-keyframe test for one frame;
* :mod:`~mslam.system.global_opt` — :class:`~mslam.system.global_opt.Backend`: the map
  (keyframes, graph, retrieval), graph construction and the global solve;
* :mod:`~mslam.system.keyframes`, :mod:`~mslam.system.edges`, :mod:`~mslam.system.graph` —
  the keyframe store, edge construction, the factor graph;
* :mod:`~mslam.system.reloc` — relocalisation; :mod:`~mslam.system.worker` — the backend in a
  background thread (``single_thread: False``);
* :mod:`~mslam.system.recovery` — a new map when relocalisation keeps failing;
* :mod:`~mslam.system.divergence`, :mod:`~mslam.system.health` — how far a run can be trusted
  (refused poses, undone solves, a map that runs away; the final checks);
* :mod:`~mslam.system.outputs` — trajectory, keyframes, PLY, summary, plot.

The call path of one frame, loop to kernel::

    run_slam → SlamSystem.process → SlamSystem.step → SlamSystem.track → Tracker.track
             → kernels.matching.match / kernels.tracking.solve / kernels.fusion.update_pointmap

Quick use::

    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.system import open_source, run_slam

    cfg = load_config()
    src = open_source("synthetic:loop:40:96x72", cfg)
    system, meta = run_slam(src, cfg, load_kernels("ref"))

Public names, in reading order:
    FrameStatus, FramePose, Mode, RunStats, SlamSystem, Source, open_source, run_slam,
    write_outputs
"""

from __future__ import annotations

from mslam.system.frontend import SlamSystem
from mslam.system.outputs import write_outputs
from mslam.system.run import run_slam
from mslam.system.sources import Source, open_source
from mslam.system.state import FramePose, FrameStatus, Mode, RunStats

__all__ = [
    "FramePose",
    "FrameStatus",
    "Mode",
    "RunStats",
    "SlamSystem",
    "Source",
    "open_source",
    "run_slam",
    "write_outputs",
]
