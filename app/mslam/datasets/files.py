"""docs/upstream.md §10.2–10.3 — the common part of every file-based loader.

A :class:`FileSequence` holds per-frame file paths, timestamps and optional ground truth, and
turns file *i* into a :class:`Frame`: read the image (and depth), undistort when the
calibration has distortion (upstream: ``K_opt`` with a centred principal point,
``initUndistortRectifyMap`` + ``remap``; depth with nearest-neighbour remapping), and
optionally resize to a working size (RGB ``INTER_AREA``, depth nearest, ``K`` rescaled with the
half-pixel rule of ``pointmap.scale_intrinsics``).

Public names, in reading order:
    FileSequence, apply_calibration
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.images import optimal_intrinsics, undistort_maps
from mslam.datasets.readers import (
    Calibration,
    colour_registration_maps,
    read_calibration,
    read_depth,
    read_rgb,
)
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import scale_intrinsics

__all__ = ["CalibrationMismatch", "FileSequence", "apply_calibration"]


class CalibrationMismatch(ValueError):
    """The images and the calibration file disagree on the image size (not a corrupt frame)."""


def apply_calibration(calib: Calibration | str | Path | None) -> Calibration | None:
    """A :class:`Calibration` from an object, a YAML path, or None."""
    if calib is None or isinstance(calib, Calibration):
        return calib
    return read_calibration(calib)


class FileSequence(FrameSequence):
    """Frames stored as image files (plus optional depth files and ground truth).

    Args:
        name: sequence name.
        rgb_paths: (N,) image files.
        timestamps: (N,) seconds.
        depth_paths: (N,) depth files or None.
        T_WC: list of (8,) poses or None per frame (ground truth), or None.
        calib: camera calibration or None (uncalibrated); its ``depth_scale`` wins over
            ``depth_scale``.
        depth_scale: raw depth units per metre.
        size: optional working size ``(W, H)`` to resize frames to.
        undistort: undistort images when the calibration has distortion (upstream does so
            whenever a calibration is used).
        center_principal_point: upstream's ``dataset.center_principle_point``.
        depth_scale_assumed: ``depth_scale`` is only the layout's convention, stated neither by
            the folder nor by ``calib`` (a TUM-layout folder from another camera); kept as
            ``self.depth_scale_assumed`` when there is depth and ``calib`` gives none.
    """

    def __init__(
        self,
        name: str,
        rgb_paths: Sequence[Path],
        timestamps: Sequence[float] | np.ndarray,
        depth_paths: Sequence[Path] | None = None,
        T_WC: Sequence[FloatArray | None] | None = None,
        calib: Calibration | None = None,
        depth_scale: float = 5000.0,
        size: tuple[int, int] | None = None,
        undistort: bool = True,
        center_principal_point: bool = True,
        depth_scale_assumed: bool = False,
    ) -> None:
        self.name = name
        self.rgb_paths = [Path(p) for p in rgb_paths]
        self.depth_paths = None if depth_paths is None else [Path(p) for p in depth_paths]
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        if len(self.rgb_paths) == 0:
            raise ValueError(f"{name}: no frames found")
        if len(self.timestamps) != len(self.rgb_paths):
            raise ValueError(f"{name}: {len(self.rgb_paths)} images but {len(timestamps)} stamps")
        self.has_depth = self.depth_paths is not None
        self._gt: list[FloatArray | None] = (
            list(T_WC) if T_WC is not None else [None] * len(self.rgb_paths)
        )
        known = [t for t in self._gt if t is not None]
        self.T_WC = np.stack(known) if known and len(known) == len(self._gt) else None
        if known and self.T_WC is None:
            nan = np.full(8, np.nan)
            self.T_WC_partial = np.stack([nan if t is None else t for t in self._gt])
        given = calib.depth_scale if calib is not None else None
        self.depth_scale = float(given or depth_scale)
        self.depth_scale_assumed = self.has_depth and depth_scale_assumed and not given
        #: The colour-to-depth registration estimated from edges (``Calibration.colour_auto``):
        #: ``zoom``, ``score``, ``identity_score``, ``applied`` (after :meth:`register_colour`).
        self.colour_registration: dict[str, float | bool] | None = None
        self.calib = calib
        self.size = None if size is None else (int(size[0]), int(size[1]))
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        #: Colour onto the depth camera's grid (``Calibration.colour``), before any resize.
        self._colour_maps = (
            None if calib is None or calib.colour is None else colour_registration_maps(calib)
        )
        self.K = None
        self.distortion = None
        if calib is not None:
            self._setup_calibration(calib, undistort, center_principal_point)

    def register_colour(self) -> None:
        """Resample the colour images onto the depth grid with colour intrinsics estimated from
        a few frames' edges, when the calibration asks for it (``colour_auto``) and they beat
        the identity (``mslam.datasets.registration``). A run calls it when it uses the
        intrinsics (RGB-D prior or ``--calib``); an uncalibrated RGB-only run has no use for
        images made to agree with intrinsics it ignores. Idempotent."""
        from mslam.datasets.registration import FRAMES, estimate_colour_intrinsics

        calib = self.calib
        if calib is None or not calib.colour_auto or self.depth_paths is None:
            return
        idx = np.unique(np.linspace(0, len(self.rgb_paths) - 1, FRAMES).round().astype(int))
        rgbs = [read_rgb(self.rgb_paths[i]) for i in idx]
        if any(im.shape[:2] != (calib.height, calib.width) for im in rgbs):
            return  # the size check of _process reports it
        depths = [read_depth(self.depth_paths[i], self.depth_scale, im.shape[:2])
                  for i, im in zip(idx, rgbs, strict=True)]  # fmt: skip
        colour, info = estimate_colour_intrinsics(calib, rgbs, depths)
        self.colour_registration = {**info, "applied": colour is not None}
        self.calib = replace(calib, colour=colour, colour_auto=False)
        if colour is not None:
            self._colour_maps = colour_registration_maps(self.calib)

    def _setup_calibration(self, calib: Calibration, undistort: bool, center: bool) -> None:
        K = calib.K
        if calib.has_distortion and undistort:
            dist = np.asarray(calib.distortion)
            K_opt = optimal_intrinsics(K, dist, calib.width, calib.height, center)
            self._maps = undistort_maps(K, dist, K_opt, calib.width, calib.height)
            K = K_opt
        elif calib.has_distortion:
            self.distortion = np.asarray(calib.distortion)
        if self.size is not None:
            K = scale_intrinsics(K, (calib.width, calib.height), self.size)
        self.K = K

    def _process(self, i: int, rgb: np.ndarray, depth: FloatArray | None) -> Frame:
        """Undistort / resize one frame and wrap it in a :class:`Frame`."""
        src = self.rgb_paths[i] if i < len(self.rgb_paths) else Path(self.name)
        if self.calib is not None and rgb.shape[:2] != (self.calib.height, self.calib.width):
            raise CalibrationMismatch(
                f"{src}: image size {rgb.shape[1]}x{rgb.shape[0]} does not match the calibration "
                f"{self.calib.width}x{self.calib.height}"
            )
        if self._colour_maps is not None:
            rgb = cv2.remap(
                rgb, *self._colour_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
        if self._maps is not None:
            mx, my = self._maps
            rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR)
            if depth is not None:
                depth = np.asarray(cv2.remap(depth, mx, my, cv2.INTER_NEAREST), np.float64)
        if self.size is not None and rgb.shape[:2] != (self.size[1], self.size[0]):
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
            if depth is not None:
                depth = np.asarray(
                    cv2.resize(depth, self.size, interpolation=cv2.INTER_NEAREST), np.float64
                )
        return Frame(i, float(self.timestamps[i]), np.ascontiguousarray(rgb), depth, self._gt[i])

    def _load(self, i: int) -> Frame:
        rgb = read_rgb(self.rgb_paths[i])
        depth = None
        if self.depth_paths is not None:
            depth = read_depth(self.depth_paths[i], self.depth_scale, rgb.shape[:2])
        return self._process(i, rgb, depth)

    def subsampled(self, step: int) -> FileSequence:
        """Every ``step``-th frame (upstream ``dataset.subsample``); indices restart at 0."""
        if int(step) < 1:
            raise ValueError(f"subsample: must be >= 1, got {step}")
        if step == 1:
            return self
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.rgb_paths = self.rgb_paths[::step]
        out.depth_paths = None if self.depth_paths is None else self.depth_paths[::step]
        out.timestamps = self.timestamps[::step]
        out._gt = self._gt[::step]
        out.T_WC = None if self.T_WC is None else self.T_WC[::step]
        out.T_WC_partial = None if self.T_WC_partial is None else self.T_WC_partial[::step]
        return out
