"""A Rerun recording of a run (``mslam run --rerun FILE.rrd``): a :class:`RunObserver`.

Timeline ``frame`` (the frame index). Entities (world = the first keyframe's camera, x right,
y down, z forward):

* ``world/camera`` — the frame's rigid pose (``Transform3D``, as ``trajectory.txt``);
  ``world/camera/image`` — the ``Pinhole`` (the run's intrinsics, given or estimated from the
  first keyframe) and the ``Image`` at the pointmap resolution; ``status`` — a ``TextLog``
  per frame (``keyframe``, ``tracked``, ``relocalised``, ``lost``, ...);
* ``world/keyframes/K`` — keyframe K's Sim(3) pose (translation, rotation, uniform scale),
  re-logged whenever the backend moves it; ``world/keyframes/K/points`` — its canonical
  pointmap in its own camera (``Points3D`` with the keyframe's colours; at most
  ``max_points`` per keyframe on a pixel grid) and ``confidence`` (C / N per point),
  re-logged as fusion refines it;
* ``world/graph/consecutive``, ``world/graph/loop_closure``, ``world/graph/reloc`` — one line
  per edge between keyframe centres, labelled ``i-j f=<match fraction>``, with the
  ``match_frac``, ``i`` and ``j`` values beside them;
* ``events/reloc`` — a ``TextLog`` per relocalisation; ``world/reloc`` — where they happened;
* static, written at the end: ``world/trajectory`` (every posed frame, final poses) and
  ``world/ground_truth`` (when the sequence has it, Sim(3)-aligned into the run's world).

Open a recording with ``rerun FILE.rrd`` (the viewer that ``pip install rerun-sdk`` installs)
or read it back with ``rerun.chunk.RrdReader``.

Public names, in reading order:
    RerunRecorder
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np

from mslam_ref.conventions import FloatArray

__all__ = ["RerunRecorder"]

#: The port a Rerun viewer listens on by default (``rerun`` / ``rerun.spawn``).
VIEWER_PORT = 9876
_EDGE_ENTITY = {"consecutive": "consecutive", "retrieval": "loop_closure", "reloc": "reloc"}
_EDGE_COLOUR = {
    "consecutive": (120, 120, 120),
    "loop_closure": (255, 140, 0),
    "reloc": (200, 0, 200),
}


def _import_rerun():
    try:
        import rerun as rr
    except ImportError:
        raise ImportError(
            "the Rerun recording needs rerun-sdk: pip install 'mslam-edu[rerun]'"
        ) from None
    return rr


class RerunRecorder:
    """Streams a run into a Rerun recording (a file, and a viewer with ``spawn``).

    Args:
        path: the ``.rrd`` file to write (None: no file).
        K: (3, 3) intrinsics at the pointmap resolution when known (calibrated mode); else
            estimated from the first keyframe's pointmap.
        spawn: also stream to a Rerun viewer: the one listening on :data:`VIEWER_PORT`, or a
            new one when a display is available (otherwise a warning, and the file only).
        max_points: at most this many points per keyframe pointmap.
        application_id: the recording's application id.
    """

    def __init__(
        self,
        path: str | Path | None,
        K: FloatArray | None = None,
        spawn: bool = False,
        max_points: int = 16384,
        application_id: str = "mslam",
    ) -> None:
        rr = self.rr = _import_rerun()
        self.rec = rr.RecordingStream(application_id)
        sinks = [rr.FileSink(str(path))] if path is not None else []
        if spawn and (_viewer_listening() or _has_display()):
            self.rec.spawn(connect=False)  # connects to a running viewer instead of a second one
            sinks.append(rr.GrpcSink())
        elif spawn:
            warnings.warn("--rerun-spawn: no display and no viewer listening on port "
                          f"{VIEWER_PORT}; open the recording later with `rerun FILE.rrd`",
                          RuntimeWarning, stacklevel=2)  # fmt: skip
        if sinks:
            self.rec.set_sinks(*sinks)
        self.K = None if K is None else np.asarray(K, np.float64)
        self.max_points = int(max_points)
        self.shape: tuple[int, int] | None = None
        self._poses = np.zeros((0, 8))
        self._edges: tuple = (np.zeros(0, np.int64), np.zeros(0, np.int64), [], np.zeros(0))
        self._relocs: list[FloatArray] = []
        self._logged: set[str] = set()
        self._closed = False
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)

    # -- RunObserver ------------------------------------------------------------------------
    def on_frame(self, i: int, image: np.ndarray, T_WC: FloatArray | None, status: str) -> None:
        """Log frame ``i``'s pose (when it has one), image and status."""
        rr = self.rr
        self.rec.set_time("frame", sequence=int(i))
        if self.shape is not None and image.shape[:2] != self.shape:
            image = cv2.resize(image, self.shape[::-1], interpolation=cv2.INTER_AREA)
        if T_WC is not None:
            T = np.asarray(T_WC, np.float64)
            self.rec.log(
                "world/camera",
                rr.Transform3D(translation=T[:3], quaternion=rr.Quaternion(xyzw=T[3:7])),
            )
        self.rec.log("world/camera/image", rr.Image(image))
        level = "WARN" if status == "lost" else "INFO"
        self.rec.log("status", rr.TextLog(f"frame {i}: {status}", level=level))

    def on_keyframe(
        self, kf_id: int, X_canon: FloatArray, C: FloatArray, colours: np.ndarray
    ) -> None:
        """Log keyframe ``kf_id``'s pointmap, colours and confidences (grid-thinned)."""
        rr = self.rr
        H, W = C.shape
        if self.shape is None:
            self.shape = (H, W)
            if self.K is None:
                from mslam.export.camera import focal_from_pointmap

                self.K = focal_from_pointmap(X_canon, C)
            self.rec.log("world/camera/image", rr.Pinhole(image_from_camera=self.K, resolution=[W, H],
                         image_plane_distance=0.1), static=True)  # fmt: skip
        stride = max(1, int(np.ceil(np.sqrt(H * W / self.max_points))))
        X = X_canon[::stride, ::stride].reshape(-1, 3)
        c = C[::stride, ::stride].reshape(-1)
        rgb = colours[::stride, ::stride].reshape(-1, 3)
        ok = np.all(np.isfinite(X), axis=-1)
        self.rec.log(f"world/keyframes/{kf_id}/points", rr.Points3D(X[ok], colors=rgb[ok], radii=-1.5),
                     rr.AnyValues(confidence=c[ok].astype(np.float32)))  # fmt: skip

    def on_keyframe_poses(self, T_WC: FloatArray) -> None:
        """Log every keyframe's Sim(3) pose and redraw the edges between their centres."""
        rr = self.rr
        T_WC = np.asarray(T_WC, np.float64)
        for k, T in enumerate(T_WC):
            if k < len(self._poses) and np.array_equal(self._poses[k], T):
                continue
            self.rec.log(f"world/keyframes/{k}", rr.Transform3D(
                translation=T[:3], quaternion=rr.Quaternion(xyzw=T[3:7]), scale=float(T[7])))  # fmt: skip
        self._poses = T_WC.copy()
        self._log_edges()

    def on_edges(
        self, ii: np.ndarray, jj: np.ndarray, kinds: list[str], match_frac: FloatArray
    ) -> None:
        """Log every graph edge, one entity per kind."""
        self._edges = (np.asarray(ii), np.asarray(jj), list(kinds), np.asarray(match_frac))
        self._log_edges()

    def on_reloc(self, i: int, kf_id: int, T_WC: FloatArray) -> None:
        """Log a relocalisation event and its position."""
        rr = self.rr
        self.rec.log(
            "events/reloc", rr.TextLog(f"frame {i} relocalised as keyframe {kf_id}", level="WARN")
        )
        self._relocs.append(np.asarray(T_WC, np.float64)[:3])
        self.rec.log(
            "world/reloc", rr.Points3D(np.array(self._relocs), colors=(200, 0, 200), radii=-6.0)
        )

    def close(self) -> None:
        """Flush and close the recording (the file is complete afterwards); idempotent."""
        if self._closed:
            return
        self._closed = True
        self.rec.flush()
        self.rec.disconnect()

    # -- the end of the run -----------------------------------------------------------------
    def log_trajectories(self, P_est: FloatArray, P_gt: FloatArray | None = None) -> None:
        """Static lines: the final estimate's camera centres (M, 3) and the ground truth's
        (G, 3), both already in the run's world frame; then the default layout, with the 3-D
        view looking down on the trajectory."""
        rr = self.rr
        P_est = np.asarray(P_est, np.float64).reshape(-1, 3)
        if len(P_est) > 1:
            self.rec.log("world/trajectory", rr.LineStrips3D([P_est], colors=(220, 40, 40)),
                         static=True)  # fmt: skip
        if P_gt is not None and len(P_gt) > 1:
            self.rec.log("world/ground_truth", rr.LineStrips3D([np.asarray(P_gt)],
                         colors=(60, 160, 60)), static=True)  # fmt: skip
        self.rec.send_blueprint(_blueprint(P_est), make_active=True)

    def _log_edges(self) -> None:
        rr = self.rr
        ii, jj, kinds, frac = self._edges
        P = self._poses[:, :3]
        for kind, name in _EDGE_ENTITY.items():
            sel = [e for e in range(len(kinds)) if kinds[e] == kind and max(ii[e], jj[e]) < len(P)]
            if not sel and name not in self._logged:
                continue
            self._logged.add(name)
            strips = [P[[ii[e], jj[e]]] for e in sel]
            labels = [f"{ii[e]}-{jj[e]} f={frac[e]:.2f}" for e in sel]
            lines = rr.LineStrips3D(
                strips, labels=labels, colors=_EDGE_COLOUR[name], show_labels=False
            )
            self.rec.log(f"world/graph/{name}", lines,
                         rr.AnyValues(match_frac=frac[sel], i=ii[sel], j=jj[sel]))  # fmt: skip


def _blueprint(P: FloatArray):
    """The map (3-D, looking down on the camera centres ``P`` (M, 3) from above and behind;
    y points down in this world), the camera image and the status/event log."""
    import rerun.blueprint as rrb

    eye = None
    if len(P):
        c = P.mean(axis=0)
        r = max(float(np.ptp(P, axis=0).max()), 1e-3)
        eye = rrb.EyeControls3D(position=c + r * np.array([0.0, -1.7, -1.2]), look_target=c,
                                eye_up=[0.0, -1.0, 0.0])  # fmt: skip
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map", eye_controls=eye),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="camera"),
                rrb.TextLogView(origin="/", name="status and events"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def _viewer_listening(port: int | None = None) -> bool:
    """Whether something accepts connections on the local viewer port."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", VIEWER_PORT if port is None else port)) == 0


def _has_display() -> bool:
    """Whether a viewer window can open (a display on Linux; always elsewhere)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
