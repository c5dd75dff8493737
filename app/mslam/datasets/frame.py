"""Paper §3 (input) — one image of a sequence and the sequence interface every loader returns.

A :class:`Frame` is what the SLAM loop receives: an index, a timestamp, an RGB image and,
when the source has them, a metric depth image and a ground-truth pose. Ground truth rides
along only so that evaluation and the *synthetic* prior can use it; the SLAM system itself
never reads ``Frame.T_WC``.

Pose choice: ``T_WC`` is stored as a Sim(3) 8-vector ``[tx, ty, tz, qx, qy, qz, qw, s]`` with
``s = 1`` (camera-to-world), the layout of :mod:`mslam_ref.sim3`, so it composes directly with
the poses the system estimates. ``sim3.to_matrix`` gives the 4x4 matrix.

Public names, in reading order:
    Frame, FrameSequence, check_frame_size
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from mslam_ref.conventions import FloatArray

__all__ = ["Frame", "FrameSequence", "check_frame_size"]


@dataclass(frozen=True, eq=False)
class Frame:
    """One input image with optional metric depth and ground-truth pose.

    Upstream: mast3r_slam/dataloader.py (``__getitem__`` returns timestamp and image) and
    frame.py::Frame (``frame_id``, ``img``, ``uimg``).

    Attributes:
        index: position in the (subsampled) sequence, upstream's ``frame_id``.
        timestamp: seconds.
        rgb: (H, W, 3) uint8 image, RGB order.
        depth: (H, W) float64 metric depth in metres (z along the optical axis), 0 where
            invalid; None when the source has no depth.
        T_WC: (8,) Sim(3) ground-truth camera-to-world pose with s = 1, or None.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: FloatArray | None = None
    T_WC: FloatArray | None = None

    def __post_init__(self) -> None:
        rgb = np.asarray(self.rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb: expected uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
        if self.depth is not None:
            d = np.asarray(self.depth)
            if d.shape != rgb.shape[:2]:
                raise ValueError(f"depth: expected shape {rgb.shape[:2]}, got {d.shape}")
            if d.dtype != np.float64 or not np.all(np.isfinite(d)):
                raise ValueError("depth: expected finite float64 metres")
        if self.T_WC is not None:
            T = np.asarray(self.T_WC)
            if T.shape != (8,) or not np.all(np.isfinite(T)):
                raise ValueError(f"T_WC: expected a finite (8,) Sim(3) vector, got {T.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the image."""
        return int(self.rgb.shape[0]), int(self.rgb.shape[1])


class FrameSequence:
    """Base class of every loader: indexable, sized, iterable frames plus metadata.

    Subclasses implement :meth:`_load(i)` for the *i*-th kept frame; this class handles the
    index checks, negative indices and iteration.

    Attributes:
        name: human-readable name (folder name, ``synthetic:loop``, ...).
        K: (3, 3) intrinsics at the image resolution, or None when unknown.
        has_depth: whether frames carry metric depth.
        timestamps: (N,) float64 seconds.
        T_WC: (N, 8) Sim(3) ground-truth poses (s = 1), or None unless every frame has one.
        T_WC_partial: (N, 8) the same with NaN rows for the frames without one, when some but
            not all frames have one (motion capture that starts late, a gap); None otherwise.
            :meth:`ground_truth` serves both.
        distortion: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3])`` of the raw
            images, or None (images already undistorted or no calibration).
    """

    name: str = ""
    K: FloatArray | None = None
    has_depth: bool = False
    timestamps: FloatArray
    T_WC: FloatArray | None = None
    T_WC_partial: FloatArray | None = None
    distortion: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.timestamps)

    def _load(self, i: int) -> Frame:  # pragma: no cover - abstract
        raise NotImplementedError

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not isinstance(i, int | np.integer):
            raise TypeError(f"index: expected an int, got {type(i).__name__}")
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"index {i} out of range for {n} frames of {self.name}")
        return self._load(int(i))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def ground_truth(self) -> tuple[np.ndarray, FloatArray, FloatArray] | None:
        """The frames that have a ground-truth pose: frame indices (M,), timestamps (M,) and
        poses (M, 8); None when no frame has one. Evaluations associate estimates with these by
        timestamp, so a sequence whose ground truth misses some frames is still evaluated."""
        T = self.T_WC if self.T_WC is not None else self.T_WC_partial
        if T is None:
            return None
        T = np.asarray(T, dtype=np.float64)
        ok = np.flatnonzero(np.isfinite(T).all(axis=1))
        if not len(ok):
            return None
        return ok, np.asarray(self.timestamps, dtype=np.float64)[ok], T[ok]

    @property
    def has_ground_truth(self) -> bool:
        """Whether ground-truth poses are available."""
        return self.T_WC is not None

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, frames={len(self)}, "
            f"calibrated={self.K is not None}, depth={self.has_depth}, "
            f"gt={self.T_WC is not None})"
        )


def check_frame_size(shape: tuple[int, int], first: tuple[int, int]) -> None:
    """Raise ``ValueError`` when an image of ``shape`` (H, W) is not the size of frame 0,
    ``first`` (H, W): a sequence's images share one size (one camera), and an image of
    another size shrunk to the working size would pass for a view through another lens."""
    if tuple(shape) != tuple(first):
        raise ValueError(
            f"image size {shape[1]}x{shape[0]} differs from frame 0's {first[1]}x{first[0]}"
        )
