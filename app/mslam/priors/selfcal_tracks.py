"""Point tracks through a stretch of video, and the frames at the detail they are tracked at.

The multi-view self-calibration (:mod:`mslam.priors.twoview_selfcal`) needs points followed
through many views. Shi–Tomasi corners (``cv2.goodFeaturesToTrack``) are followed from frame
to frame by pyramidal Lucas–Kanade (``cv2.calcOpticalFlowPyrLK``); a track ends where the
backward flow does not return within ``FB_PX`` pixels or the point leaves the image, and new
corners away from the living tracks keep ``CORNERS`` of them alive. Every frame of the stretch
is tracked (not only the views) so that each step is short.

The run's frames are small (160x120 by default); a focal length and a weak lens need more
detail: on the clip re-rendered at 55° and 50° (``benchmarks/novel_views.py``) the estimate
was 4.9 % short and 2.7 % long from 160x120 tracks, within 1 % from 320x240 ones
(benchmarks/RESULTS.md, "The camera from many views"). :func:`detail_frames` reads the
source's own images and shrinks them to ``DETAIL_SIDE`` pixels on the long side (never
enlarging).

Public names, in reading order:
    DETAIL_SIDE, Tracks, detail_frames, track
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from mslam.datasets.frame import FrameSequence
from mslam.datasets.views import ResizedSequence
from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["DETAIL_SIDE", "Tracks", "detail_frames", "track"]

#: Long side of the frames the tracks are followed in (pixels).
DETAIL_SIDE = 320
#: Corners kept alive, and the largest forward–backward disagreement of a kept step (pixels).
CORNERS = 500
FB_PX = 0.5
_WIN, _LEVELS = (11, 11), 3
_STOP = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)


@dataclass(frozen=True)
class Tracks:
    """Observations of point tracks (O observations).

    Attributes:
        track: (O,) track id. frame: (O,) position of the frame in the tracked stretch.
        uv: (O, 2) pixels. size: ``(W, H)`` of the tracked frames.
    """

    track: IntArray
    frame: IntArray
    uv: FloatArray
    size: tuple[int, int]


def detail_frames(sequence: FrameSequence) -> Callable[[int], np.ndarray]:
    """``gray(i)``: frame ``i`` of ``sequence`` as an (H, W) uint8 image with the long side at
    most ``DETAIL_SIDE``, read from the source's own images when the run shrinks them."""
    resized: ResizedSequence | None = None
    seq: FrameSequence | None = sequence  # the views above a ResizedSequence keep indices
    while resized is None and seq is not None:
        resized = seq if isinstance(seq, ResizedSequence) else None
        seq = getattr(seq, "base", None)
    source = resized.base if resized is not None else sequence

    def gray(i: int) -> np.ndarray:
        rgb = source[i].rgb
        H, W = rgb.shape[:2]
        f = min(1.0, DETAIL_SIDE / max(W, H))
        if f < 1.0:
            rgb = cv2.resize(rgb, (round(W * f), round(H * f)), interpolation=cv2.INTER_AREA)
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)

    return gray


def _new_corners(gray: np.ndarray, living: np.ndarray, n: int, spacing: int) -> np.ndarray:
    """Up to ``n`` corners (N, 2) at least ``spacing`` pixels from the ``living`` points."""
    mask = np.full(gray.shape, 255, np.uint8)
    for u, v in living:
        cv2.circle(mask, (int(u), int(v)), spacing, 0, -1)
    found = cv2.goodFeaturesToTrack(gray, n, 0.01, spacing, mask=mask, blockSize=5)
    return np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2)


def _lk(a: np.ndarray, b: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas–Kanade of points (N, 1, 2) float32 from a to b: positions, status."""
    out, st, _ = cv2.calcOpticalFlowPyrLK(
        a, b, pts, pts.copy(), winSize=_WIN, maxLevel=_LEVELS, criteria=_STOP
    )
    return np.asarray(out), np.asarray(st)


def _follow(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``pts`` (N, 2) float32 followed from ``prev`` to ``cur``: new positions and a kept mask."""
    H, W = cur.shape
    fwd, st = _lk(prev, cur, pts.reshape(-1, 1, 2))
    back, st2 = _lk(cur, prev, fwd)
    fwd, back = fwd.reshape(-1, 2), back.reshape(-1, 2)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - pts, axis=1) < FB_PX)
    ok &= (fwd[:, 0] >= 0) & (fwd[:, 0] <= W - 1) & (fwd[:, 1] >= 0) & (fwd[:, 1] <= H - 1)
    return fwd, ok


def track(grays: Sequence[np.ndarray]) -> Tracks:
    """Tracks through consecutive frames ``grays`` ((H, W) uint8 each), module docstring."""
    H, W = grays[0].shape
    spacing = max(3, round(min(W, H) / 30))
    pts, ids, next_id = np.zeros((0, 2), np.float32), np.zeros(0, np.int64), 0
    obs_id, obs_frame, obs_uv = [], [], []
    for n, gray in enumerate(grays):
        if n and len(pts):
            pts, ok = _follow(grays[n - 1], gray, pts)
            pts, ids = pts[ok], ids[ok]
        if len(pts) < 0.8 * CORNERS:
            new = _new_corners(gray, pts, CORNERS - len(pts), spacing)
            pts = np.vstack([pts, new]).astype(np.float32)
            ids = np.concatenate([ids, np.arange(next_id, next_id + len(new))])
            next_id += len(new)
        obs_id.append(ids)
        obs_frame.append(np.full(len(ids), n))
        obs_uv.append(pts.astype(np.float64))
    return Tracks(np.concatenate(obs_id), np.concatenate(obs_frame), np.concatenate(obs_uv),
                  (W, H))  # fmt: skip
