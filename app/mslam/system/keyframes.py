"""Paper §3.4 (docs/upstream.md §1.3) — the keyframe store: frames, poses, fused pointmaps.

The keyframe store holds, per keyframe, the input frame, its Sim(3) pose ``T_WC``, its fused
canonical pointmap (``PointmapState``) and its retrieval features. Unlike upstream's
``SharedKeyframes`` (512 slots preallocated on the GPU, the cause of the out-of-memory reports
of docs/upstream.md §14) it is a Python list that grows one keyframe at a time.

Public names, in reading order:
    Keyframe, KeyframeStore
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from mslam.datasets.frame import Frame
from mslam_ref.conventions import FloatArray, IntArray
from mslam_ref.fusion import PointmapState

__all__ = ["Keyframe", "KeyframeStore"]


@dataclass(eq=False)
class Keyframe:
    """One keyframe (upstream frame.py::Frame as stored in ``SharedKeyframes``).

    Attributes:
        frame: the input frame (index, timestamp, rgb, ...).
        T_WC: (8,) Sim(3) camera-to-world pose, updated by the backend.
        state: the fused canonical pointmap (``mslam_ref.fusion.PointmapState``: X_canon (N, 3),
            C (N,) accumulated confidence, N, N_updates, score).
        shape: (H, W) of the pointmap.
        features: (nfeat, F) retrieval features, or None.
        T_WC_init: (8,) the pose the keyframe was created with (tracking or relocalisation,
            before any backend solve), kept for plots and diagnostics.
        X_map: (N, 3) the points the map exports: ``state.X_canon`` fused with the same weights
            but without filled-in points (``mslam.system.tracker.without_filler``); tracking
            and the backend use ``state`` as upstream does.
    """

    frame: Frame
    T_WC: FloatArray
    state: PointmapState
    shape: tuple[int, int]
    features: FloatArray | None = None
    T_WC_init: FloatArray | None = None
    X_map: FloatArray | None = None

    def __post_init__(self) -> None:
        if self.T_WC_init is None:
            self.T_WC_init = np.asarray(self.T_WC, dtype=np.float64).copy()
        if self.X_map is None:
            self.X_map = np.asarray(self.state.X_canon, dtype=np.float64).copy()

    def retrieval_features(self) -> FloatArray:
        """(nfeat, F) ``features``; a keyframe of the map always has them (``add_keyframe``
        computes them), so their absence is a programming error, raised as one."""
        if self.features is None:
            raise RuntimeError(
                f"the keyframe of frame {self.frame.index} has no retrieval features"
            )
        return self.features

    def points(self, exported: bool = False) -> FloatArray:
        """(N, 3) ``state.X_canon``, or with ``exported`` the map's points ``X_map``."""
        X = self.X_map if exported else self.state.X_canon
        return np.asarray(X if X is not None else self.state.X_canon, dtype=np.float64)


class KeyframeStore:
    """Keyframes in creation order; grows one at a time (no preallocated buffer).

    Upstream: frame.py::SharedKeyframes (``append``, ``pop_last``, ``last_keyframe``,
    ``update_T_WCs``).
    """

    def __init__(self) -> None:
        self._kfs: list[Keyframe] = []

    def __len__(self) -> int:
        return len(self._kfs)

    def __getitem__(self, i: int) -> Keyframe:
        return self._kfs[i]

    def __iter__(self) -> Iterator[Keyframe]:
        return iter(self._kfs)

    def append(self, kf: Keyframe) -> int:
        """Add a keyframe; returns its index."""
        if self._kfs and kf.shape != self._kfs[0].shape:
            raise ValueError(f"kf: pointmap shape {kf.shape} differs from {self._kfs[0].shape}")
        self._kfs.append(kf)
        return len(self._kfs) - 1

    def pop_last(self) -> Keyframe:
        """Remove and return the last keyframe (a failed relocalisation)."""
        return self._kfs.pop()

    def last(self) -> Keyframe:
        """The most recent keyframe (upstream ``last_keyframe``)."""
        return self._kfs[-1]

    def poses(self) -> FloatArray:
        """(K, 8) Sim(3) poses of all keyframes."""
        return np.stack([kf.T_WC for kf in self._kfs]) if self._kfs else np.zeros((0, 8))

    def set_poses(self, T_WC: FloatArray, indices: IntArray | None = None) -> None:
        """Write back poses (upstream ``update_T_WCs``); ``indices`` default to all."""
        T_WC = np.asarray(T_WC, dtype=np.float64)
        indices = np.arange(len(self._kfs)) if indices is None else np.asarray(indices)
        for k, T in zip(indices, T_WC, strict=True):
            self._kfs[int(k)].T_WC = T.copy()

    def pointmaps(
        self,
        fusion: ModuleType,
        K: FloatArray | None = None,
        exported: bool = False,
        indices: IntArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Stacked canonical pointmaps and average confidences of the keyframes.

        Args:
            fusion: the ``mslam_ref.fusion`` module (for ``average_confidence``).
            K: (3, 3) intrinsics in calibrated mode: points are constrained to the known rays
                (``mslam_ref.calib.constrain_points_to_ray``), as upstream's ``solve_GN_calib``.
            exported: the map's points (``Keyframe.X_map``) instead of ``state.X_canon``.
            indices: (K',) the keyframes to stack, in that order (default: all).

        Returns:
            X (K', H, W, 3) and C (K', H, W) = C / N.
        """
        H, W = self._kfs[0].shape
        kfs = self._kfs if indices is None else [self._kfs[int(k)] for k in indices]
        X = np.stack([kf.points(exported).reshape(H, W, 3) for kf in kfs])
        C = np.stack([np.asarray(fusion.average_confidence(kf.state)).reshape(H, W) for kf in kfs])
        if K is not None:
            from mslam_ref.calib import constrain_points_to_ray

            X = np.stack([constrain_points_to_ray(x, K) for x in X])
        return X, C
