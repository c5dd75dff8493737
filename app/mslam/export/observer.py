"""What a run shows while it runs: a narrow observer interface and the tap that feeds it.

:class:`RunObserver` is the interface a viewer or recorder implements; every argument is a plain
array, a number or a string, never a system object:

* ``on_frame(i, image, T_WC, status)`` — every processed frame;
* ``on_keyframe(kf_id, X_canon, C, colours)`` — a new keyframe, or its pointmap refined by fusion;
* ``on_keyframe_poses(T_WC)`` — the keyframe poses after the backend moved them;
* ``on_edges(ii, jj, kinds, match_frac)`` — the graph's edges whenever they change;
* ``on_reloc(i, kf_id, T_WC)`` — a relocalisation;
* ``close()`` — the end of the run.

:class:`SystemTap` is the only code that reads a :class:`~mslam.system.SlamSystem`'s fields: the
SLAM loop calls ``tap.after_frame(i, frame, system, status)`` once per processed frame, and the
tap turns what changed since the previous call into the calls above. Keyframe pointmaps change
on every fused frame; the tap sends a refined pointmap at most every ``refine_every`` frames per
keyframe and every pending one in :meth:`SystemTap.finish`.

Public names, in reading order:
    RunObserver, keyframe_colours, SystemTap
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from mslam.system.outputs import keyframe_colours
from mslam_ref import sim3
from mslam_ref.conventions import FloatArray

if TYPE_CHECKING:
    from mslam.datasets.frame import Frame
    from mslam.system.frontend import SlamSystem
    from mslam.system.state import FrameStatus

__all__ = ["RunObserver", "SystemTap", "keyframe_colours"]


class RunObserver(Protocol):
    """Receives a run's events; shapes use H, W (pointmap), K keyframes, E edges."""

    def on_frame(self, i: int, image: np.ndarray, T_WC: FloatArray | None, status: str) -> None:
        """Frame ``i``: (h, w, 3) uint8 RGB, (8,) Sim(3) camera-to-world or None when lost,
        status ``keyframe``/``tracked``/``relocalised``/``lost``/``rotation``/``waiting``."""

    def on_keyframe(
        self, kf_id: int, X_canon: FloatArray, C: FloatArray, colours: np.ndarray
    ) -> None:
        """Keyframe ``kf_id``'s canonical pointmap (H, W, 3) in its camera, average confidence
        C / N (H, W) and colours (H, W, 3) uint8."""

    def on_keyframe_poses(self, T_WC: FloatArray) -> None:
        """(K, 8) Sim(3) poses of all keyframes."""

    def on_edges(
        self, ii: np.ndarray, jj: np.ndarray, kinds: list[str], match_frac: FloatArray
    ) -> None:
        """All graph edges: (E,) keyframe indices, kinds (``consecutive``, ``retrieval``,
        ``reloc``) and (E,) match fractions."""

    def on_reloc(self, i: int, kf_id: int, T_WC: FloatArray) -> None:
        """Frame ``i`` was relocalised as keyframe ``kf_id`` at (8,) ``T_WC``."""

    def close(self) -> None:
        """The run is over."""


def _keyframe_pointmap(system: SlamSystem, k: int) -> tuple[FloatArray, FloatArray]:
    """Keyframe ``k``'s X_canon (H, W, 3) (on the known rays in calibrated mode) and C / N (H, W)."""
    from mslam_ref import fusion

    kf = system.keyframes[k]
    H, W = kf.shape
    X = np.asarray(kf.state.X_canon, np.float64).reshape(H, W, 3)
    if system.K is not None:
        from mslam_ref.calib import constrain_points_to_ray

        X = constrain_points_to_ray(X, system.K)
    C = np.asarray(fusion.average_confidence(kf.state), np.float64).reshape(H, W)
    return X, C


class SystemTap:
    """Turns the system's state after each frame into :class:`RunObserver` calls.

    Args:
        observer: the receiver.
        refine_every: send a keyframe's refined pointmap at most every this many frames.
    """

    def __init__(self, observer: RunObserver, refine_every: int = 5) -> None:
        self.observer = observer
        self.refine_every = max(1, int(refine_every))
        self._states: dict[int, Any] = {}  # keyframe -> the pointmap state last sent
        self._sent_at: dict[int, int] = {}  # keyframe -> frame at which it was last sent
        self._poses = np.zeros((0, 8))
        self._edges: tuple = ()

    def after_frame(self, i: int, frame: Frame, system: SlamSystem, status: FrameStatus) -> None:
        """Report frame ``i`` (the :class:`~mslam.datasets.frame.Frame` just processed)."""
        with system.backend.lock:
            rec = system.poses[-1] if system.poses else None
            T_WC = None
            if rec is not None and rec.index == frame.index and 0 <= rec.kf < len(system.keyframes):
                T_WC = sim3.mul(system.keyframes[rec.kf].T_WC, rec.T_CkCf)
            self.observer.on_frame(i, frame.rgb, T_WC, status)
            self._send_keyframes(system, i, force=False)
            self._send_poses_and_edges(system)
            if status == "relocalised" and rec is not None and T_WC is not None:
                self.observer.on_reloc(i, rec.kf, T_WC)

    def finish(self, system: SlamSystem) -> None:
        """Send every pointmap refined since it was last sent, the final poses and edges."""
        with system.backend.lock:
            self._send_keyframes(system, None, force=True)
            self._send_poses_and_edges(system)

    def _send_keyframes(self, system: SlamSystem, i: int | None, force: bool) -> None:
        n = len(system.keyframes)
        for k in [k for k in self._states if k >= n]:  # a relocalisation was undone
            del self._states[k], self._sent_at[k]
        for k in range(n):
            state = system.keyframes[k].state
            if self._states.get(k) is state:
                continue
            due = k not in self._sent_at or force
            due = due or (i is not None and i - self._sent_at[k] >= self.refine_every)
            if not due:
                continue
            X, C = _keyframe_pointmap(system, k)
            self.observer.on_keyframe(k, X, C, keyframe_colours(system, k))
            self._states[k] = state
            self._sent_at[k] = -1 if i is None else i

    def _send_poses_and_edges(self, system: SlamSystem) -> None:
        T = system.keyframes.poses()
        if T.shape != self._poses.shape or not np.array_equal(T, self._poses):
            self._poses = T.copy()
            self.observer.on_keyframe_poses(T)
        edges = tuple((e.i, e.j, e.kind, e.match_frac) for e in system.graph.edges)
        if edges != self._edges:
            self._edges = edges
            ii = np.array([e[0] for e in edges], np.int64)
            jj = np.array([e[1] for e in edges], np.int64)
            frac = np.array([e[3] for e in edges], np.float64)
            self.observer.on_edges(ii, jj, [e[2] for e in edges], frac)
