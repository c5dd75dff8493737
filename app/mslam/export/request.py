"""What ``mslam run --rerun/--colmap/--depth`` asks for, checked up front and written into the set.

Every export lies inside the one output set of ``mslam run`` (``mslam.outdir``):

* the Rerun recording streams, while the run goes, into a hidden temporary file beside
  ``--out`` (``.OUT.mslam-tmp-rerun-PID``, removed on any error and by the next run into the
  same target if the process was killed) and is moved into the staged set at the end;
* the COLMAP model and the depth maps are written from the final state into the staged set.

So a fault leaves either nothing or one whole set, recording included.

Public names, in reading order:
    ExportRequest
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mslam.datasets.frame import FrameSequence
from mslam.system.frontend import SlamSystem

__all__ = ["ExportRequest"]

#: Names in the output set that ``write_outputs`` owns (an export may not take them).
RESERVED = ("trajectory.txt", "keyframes.txt", "keyframes", "baseline_odometry.txt",
            "reconstruction.ply", "summary.json", "trajectory.png", "depth")  # fmt: skip


def _inside(out: Path, path: str | None, flag: str) -> Path | None:
    """``path`` relative to ``out``; a path outside it (or a reserved name) is a ValueError."""
    if path is None:
        return None
    p, o = Path(os.path.abspath(path)), Path(os.path.abspath(out))
    if p == o or not p.is_relative_to(o):
        raise ValueError(f"{flag} {path}: must name a path inside --out {out} (e.g. {out}/run.rrd)")
    rel = p.relative_to(o)
    if rel.parts[0] in RESERVED:
        raise ValueError(f"{flag} {path}: {rel.parts[0]} is one of the run's own outputs")
    return rel


_ESTIMATED = "estimated from the keyframe pointmaps (mslam.export.camera)"


@dataclass
class ExportRequest:
    """The exports of one ``mslam run``; paths are relative to the output set.

    Attributes:
        out: the ``--out`` folder.
        rerun: the recording's path in the set, or None.
        spawn: also stream to a viewer.
        colmap: the COLMAP folder in the set, or None.
        colmap_all_frames: one image per posed frame instead of per keyframe.
        depth: write ``depth/`` (``mslam.export.depth``).
    """

    out: Path
    rerun: Path | None = None
    spawn: bool = False
    colmap: Path | None = None
    colmap_all_frames: bool = False
    depth: bool = False

    def __post_init__(self) -> None:
        self._recorder: Any = None
        self._tap: Any = None
        self._tmp: Path | None = None

    @classmethod
    def from_args(cls, out: Path, args: Any) -> ExportRequest:
        """Check the options before any work; bad ones are a one-line :class:`ValueError`."""
        rerun = _inside(out, getattr(args, "rerun", None), "--rerun")
        colmap = _inside(out, getattr(args, "colmap", None), "--colmap")
        if rerun is not None and rerun.suffix != ".rrd":
            raise ValueError(f"--rerun {args.rerun}: expected a file name ending in .rrd")
        if rerun is not None and colmap is not None and rerun.is_relative_to(colmap):
            raise ValueError(f"--rerun {args.rerun}: lies inside --colmap {args.colmap}")
        req = cls(out, rerun, bool(getattr(args, "rerun_spawn", False)), colmap,
                  getattr(args, "colmap_images", "keyframes") == "frames", bool(getattr(args, "depth", False)))  # fmt: skip
        if req.rerun is not None or req.spawn:
            from mslam.export.rerun_log import _import_rerun

            try:
                _import_rerun()
            except ImportError as exc:
                raise ValueError(f"--rerun: {exc}") from None
        return req

    def _tmp_recording(self) -> Path:
        out = Path(os.path.abspath(self.out))
        out.parent.mkdir(parents=True, exist_ok=True)
        return out.with_name(f".{out.name}.mslam-tmp-rerun-{os.getpid()}")

    @contextlib.contextmanager
    def recording(self, K: Any = None) -> Iterator[Any]:
        """Yield a :class:`~mslam.export.observer.SystemTap` feeding the recorder (None when no
        recording was asked for); the temporary file is removed on leaving, whatever happens."""
        if self.rerun is None and not self.spawn:
            yield None
            return
        from mslam.export.observer import SystemTap
        from mslam.export.rerun_log import RerunRecorder

        self._tmp = self._tmp_recording() if self.rerun is not None else None
        self._recorder = RerunRecorder(self._tmp, K=K, spawn=self.spawn)
        self._tap = SystemTap(self._recorder)
        try:
            yield self._tap
        finally:
            self._recorder.close()
            if self._tmp is not None:
                self._tmp.unlink(missing_ok=True)

    def write(self, stage: Path, system: SlamSystem, sequence: FrameSequence) -> dict[str, Any]:
        """Write the exports into the staged set ``stage``; returns what was written."""
        done: dict[str, Any] = {}
        K, origin = None, ""
        if self.colmap is not None or self.depth:
            from mslam.export.camera import run_intrinsics

            if len(system.keyframes):
                K, given = run_intrinsics(system)
                origin = "given (calibrated mode)" if given else _ESTIMATED
        if self._tap is not None:
            self._finish_recording(system, sequence)
            if self.rerun is not None and self._tmp is not None:
                (stage / self.rerun).parent.mkdir(parents=True, exist_ok=True)
                shutil.move(self._tmp, stage / self.rerun)
                done["rerun"] = str(self.rerun)
        if self.colmap is not None and K is not None:
            from mslam.export.colmap import write_colmap

            model = write_colmap(
                stage / self.colmap, system, sequence, K, self.colmap_all_frames, origin
            )
            done["colmap"] = {"images": len(model.names), "points3D": len(model.xyz)}
        if self.depth and K is not None:
            from mslam.export.depth import write_depth_maps

            done["depth"] = write_depth_maps(stage / "depth", system, K, origin)
        return done

    def _finish_recording(self, system: SlamSystem, sequence: FrameSequence) -> None:
        """Pending pointmaps, the final trajectory, the aligned ground truth; then close."""
        self._tap.finish(system)
        _, ts, T = system.frame_poses()
        self._recorder.log_trajectories(T[:, :3], _aligned_ground_truth(ts, T, sequence))
        self._recorder.close()


def _aligned_ground_truth(
    ts: np.ndarray, T: np.ndarray, sequence: FrameSequence
) -> np.ndarray | None:
    """Ground-truth positions (G, 3) moved into the run's world by the inverse Sim(3) alignment
    of the estimate onto the ground truth (``gt ≈ s R p + t``)."""
    gt = getattr(sequence, "T_WC", None)
    if gt is None or len(T) < 3:
        return None
    from mslam import evaluate

    gt = np.asarray(gt, np.float64)
    try:
        res = evaluate.ate(ts, T, np.asarray(sequence.timestamps, np.float64), gt, align="sim3")
    except ValueError:
        return None
    return (gt[:, :3] - res.translation) @ res.rotation / res.scale
