"""Views of a frame sequence: every n-th frame, smaller images, the first n frames.

Each view is itself a :class:`~mslam.datasets.frame.FrameSequence` over another one, so the
one input pipeline (``mslam.datasets.load_sequence`` then ``mslam.system.sources.open_source``)
composes them in a fixed order: subsample, resize, truncate.

``DivisionUndistortedSequence`` comes last, after a run has estimated its lens
(``mslam.priors.twoview_lens``).

Public names, in reading order:
    SubsampledSequence, ResizedSequence, TruncatedSequence, DivisionUndistortedSequence
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from mslam.datasets.frame import Frame, FrameSequence, check_frame_size
from mslam.datasets.images import division_maps
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import scale_intrinsics

__all__ = [
    "DivisionUndistortedSequence",
    "ResizedSequence",
    "SubsampledSequence",
    "TruncatedSequence",
]


def _rows(T: FloatArray | None, keep: np.ndarray | slice) -> FloatArray | None:
    """The rows ``keep`` of the per-frame poses ``T`` (N, 8), or None."""
    return None if T is None else np.asarray(T)[keep]


def _copy_metadata(view: FrameSequence, base: FrameSequence) -> None:
    """Name, intrinsics, depth, distortion, image size, colour registration and the partial
    ground truth (views that drop frames slice the latter again)."""
    view.name, view.K = base.name, base.K
    view.T_WC_partial = base.T_WC_partial
    view.has_depth, view.distortion = base.has_depth, base.distortion
    for attr in ("width", "height", "colour_registration"):
        if hasattr(base, attr):
            setattr(view, attr, getattr(base, attr))


class SubsampledSequence(FrameSequence):
    """Every ``step``-th frame of ``base`` (upstream ``dataset.subsample``); frame indices are
    renumbered 0, 1, ... as upstream's ``frame_id``; timestamps and ground truth are kept."""

    def __init__(self, base: FrameSequence, step: int) -> None:
        if int(step) < 1:
            raise ValueError(f"subsample: must be >= 1, got {step}")
        self.base, self.step = base, int(step)
        _copy_metadata(self, base)
        self._keep = np.arange(0, len(base), self.step)
        self.timestamps = np.asarray(base.timestamps)[self._keep]
        self.T_WC = _rows(base.T_WC, self._keep)
        self.T_WC_partial = _rows(base.T_WC_partial, self._keep)

    def _load(self, i: int) -> Frame:
        return dataclasses.replace(self.base[int(self._keep[i])], index=i)


class ResizedSequence(FrameSequence):
    """Frames of ``base`` shrunk to ``(width, height)``: colour with INTER_AREA, depth with
    nearest neighbour (no mixing across depth edges), intrinsics rescaled (pixel centres).
    A frame whose size is not ``src_size`` (the first frame's) raises ``ValueError``
    (``mslam.datasets.frame.check_frame_size``)."""

    def __init__(self, base: FrameSequence, width: int, height: int, src_size: tuple[int, int]):
        self.base = base
        _copy_metadata(self, base)
        self.width, self.height = int(width), int(height)
        self.src_size = (int(src_size[0]), int(src_size[1]))
        self.timestamps, self.T_WC = base.timestamps, base.T_WC
        self.K = None if base.K is None else scale_intrinsics(base.K, src_size, (width, height))

    def _load(self, i: int) -> Frame:
        f = self.base[i]
        check_frame_size(f.shape, (self.src_size[1], self.src_size[0]))
        size = (self.width, self.height)
        rgb = cv2.resize(f.rgb, size, interpolation=cv2.INTER_AREA)
        depth: FloatArray | None = None
        if f.depth is not None:  # float64 in, float64 out
            depth = np.asarray(
                cv2.resize(f.depth, size, interpolation=cv2.INTER_NEAREST), np.float64
            )
        return dataclasses.replace(f, rgb=rgb, depth=depth)


class TruncatedSequence(FrameSequence):
    """The first ``n`` frames of ``base`` (``mslam run --max-frames``)."""

    def __init__(self, base: FrameSequence, n: int) -> None:
        self.base = base
        _copy_metadata(self, base)
        self.timestamps = np.asarray(base.timestamps)[:n]
        self.T_WC = _rows(base.T_WC, slice(0, n))
        self.T_WC_partial = _rows(base.T_WC_partial, slice(0, n))

    def _load(self, i: int) -> Frame:
        return self.base[i]


class DivisionUndistortedSequence(FrameSequence):
    """Frames of an uncalibrated ``base`` undistorted by the division model ``lam``
    (``mslam.datasets.images.division_maps``): colour bilinear, depth nearest neighbour."""

    def __init__(self, base: FrameSequence, lam: float) -> None:
        self.base, self.lam = base, float(lam)
        _copy_metadata(self, base)
        self.timestamps, self.T_WC = base.timestamps, base.T_WC
        self._maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def _load(self, i: int) -> Frame:
        f = self.base[i]
        H, W = f.shape
        if (W, H) not in self._maps:
            self._maps[(W, H)] = division_maps(self.lam, W, H)
        mx, my = self._maps[(W, H)]
        rgb = cv2.remap(f.rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        depth: FloatArray | None = None
        if f.depth is not None:
            depth = np.asarray(cv2.remap(f.depth, mx, my, cv2.INTER_NEAREST), np.float64)
        return dataclasses.replace(f, rgb=rgb, depth=depth)
