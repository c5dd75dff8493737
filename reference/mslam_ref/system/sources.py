"""Spec §10 — opening a SOURCE for ``mslam run``: sequence, calibration and prior, checked first.

``open_source`` resolves everything a run needs *before any work starts*, so that a bad path,
a missing or inconsistent calibration, or a prior that cannot work on the source is one clear
error (``ValueError``/``FileNotFoundError``) and no output is written:

* SOURCE ``None`` → the built-in synthetic ``loop`` (:data:`DEFAULT_SYNTHETIC`);
  ``synthetic:NAME[:FRAMES[:WxH]]`` → ``mslam_ref.synthetic.make_sequence``; anything else
  → ``mslam_ref.datasets.load_sequence`` (TUM-layout folder, 7-Scenes folder, image folder,
  video file).
* ``--calib FILE`` (upstream: forces ``use_calib``) sets the intrinsics; its ``width``/``height``
  must match the images. ``use_calib`` without any intrinsics is an error.
* Prior: ``synthetic`` for synthetic sources, ``rgbd`` when the frames carry depth, otherwise
  ``mast3r`` or ``twoview`` (RGB only, ignores depth; K only when calibrated) must be asked
  for explicitly; a depth-less source without one is an error.
* ``dataset.long_side`` shrinks frames (never enlarges) so the long side has that many pixels,
  with the intrinsics rescaled; ``dataset.subsample`` keeps every n-th frame.

Public names, in reading order:
    DEFAULT_SYNTHETIC, PRIORS, Source, parse_synthetic, ResizedSequence, SubsampledSequence,
    open_source
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mslam_ref.config import SlamConfig
from mslam_ref.datasets.frame import Frame, FrameSequence

__all__ = [
    "DEFAULT_SYNTHETIC",
    "PRIORS",
    "ResizedSequence",
    "Source",
    "SubsampledSequence",
    "open_source",
    "parse_synthetic",
]

#: The built-in sequence of ``mslam run --out DIR`` (name, frames, width, height).
DEFAULT_SYNTHETIC = ("loop", 72, 128, 96)

#: Accepted ``--prior`` values.
PRIORS = ("synthetic", "rgbd", "mast3r", "twoview")


@dataclass
class Source:
    """What a run needs from its input.

    Attributes:
        sequence: the (resized, subsampled) frames.
        prior: the prior instance. prior_name: its name.
        K: (3, 3) intrinsics at the frame resolution when calibrated, else None.
        name: human-readable source name.
    """

    sequence: Any
    prior: Any
    prior_name: str
    K: np.ndarray | None
    name: str


def parse_synthetic(source: str) -> tuple[str, int, int, int]:
    """``synthetic:NAME[:FRAMES[:WxH]]`` → (name, frames, width, height); defaults from
    :data:`DEFAULT_SYNTHETIC`."""
    parts = source.split(":")
    name = parts[1] if len(parts) > 1 and parts[1] else DEFAULT_SYNTHETIC[0]
    n, w, h = DEFAULT_SYNTHETIC[1:]
    try:
        if len(parts) > 2:
            n = int(parts[2])
        if len(parts) > 3:
            w, h = (int(x) for x in parts[3].lower().split("x"))
        if len(parts) > 4:
            raise ValueError
    except ValueError:
        raise ValueError(f"SOURCE {source!r}: expected synthetic:NAME[:FRAMES[:WxH]]") from None
    if n < 2 or w < 16 or h < 16:
        raise ValueError(f"SOURCE {source!r}: need >= 2 frames and >= 16x16 pixels")
    return name, n, w, h


class SubsampledSequence(FrameSequence):
    """Every ``step``-th frame of ``base`` (upstream ``dataset.subsample``); frame indices are
    renumbered 0, 1, ... as upstream's ``frame_id``; timestamps and ground truth are kept."""

    def __init__(self, base: FrameSequence, step: int) -> None:
        self.base, self.step = base, int(step)
        self.name = base.name
        self.K, self.has_depth, self.distortion = base.K, base.has_depth, base.distortion
        keep = np.arange(0, len(base), self.step)
        self._keep = keep
        self.timestamps = np.asarray(base.timestamps)[keep]
        self.T_WC = None if base.T_WC is None else np.asarray(base.T_WC)[keep]
        for attr in ("width", "height"):
            if hasattr(base, attr):
                setattr(self, attr, getattr(base, attr))

    def _load(self, i: int) -> Frame:
        return dataclasses.replace(self.base[int(self._keep[i])], index=i)


class ResizedSequence(FrameSequence):
    """Frames of ``base`` shrunk to ``(width, height)``: colour with INTER_AREA, depth with
    nearest neighbour (no mixing across depth edges), intrinsics rescaled (pixel centres)."""

    def __init__(self, base: FrameSequence, width: int, height: int, src_size: tuple[int, int]):
        from mslam_ref.pointmap import scale_intrinsics

        self.base, self.width, self.height = base, int(width), int(height)
        self.name = base.name
        self.has_depth, self.distortion = base.has_depth, base.distortion
        self.timestamps, self.T_WC = base.timestamps, base.T_WC
        self.K = None if base.K is None else scale_intrinsics(base.K, src_size, (width, height))

    def _load(self, i: int) -> Frame:
        f = self.base[i]
        size = (self.width, self.height)
        rgb = cv2.resize(f.rgb, size, interpolation=cv2.INTER_AREA)
        depth = None
        if f.depth is not None:
            depth = cv2.resize(f.depth, size, interpolation=cv2.INTER_NEAREST)
        return dataclasses.replace(f, rgb=rgb, depth=depth)


def _make_prior(name: str, sequence: Any, use_calib: bool = False) -> Any:
    if name == "twoview":
        from mslam_ref.priors.twoview import TwoViewPrior

        if not use_calib:
            return TwoViewPrior()  # focal-length guess (priors/twoview_geometry.py)
        H, W = _first_readable(sequence, sequence.name or "source").shape
        return TwoViewPrior(sequence.K, (W, H))
    if name == "synthetic":
        from mslam_ref.priors.synthetic import SyntheticPrior

        return SyntheticPrior(sequence)
    if name == "rgbd":
        from mslam_ref.priors import rgbd

        return rgbd.RGBDPrior(sequence)
    from mslam_ref.priors import mast3r

    return mast3r.load_prior()  # checkpoint from $MSLAM_MAST3R_CHECKPOINT


def open_source(
    source: str | None,
    cfg: SlamConfig,
    calib: str | Path | None = None,
    prior: str | None = None,
    max_frames: int | None = None,
) -> Source:
    """Open and check a run's input (module docstring); raises before any work on bad input."""
    if prior is not None and prior not in PRIORS:
        raise ValueError(f"--prior: unknown prior {prior!r}; choose one of {', '.join(PRIORS)}")
    cal = None
    if calib is not None:
        from mslam_ref.datasets.io import read_calibration

        cal = read_calibration(calib)
    synthetic = source is None or str(source).startswith("synthetic")
    if synthetic:
        from mslam_ref.synthetic import make_sequence

        name, n, w, h = parse_synthetic(source or "synthetic:")
        seq: Any = make_sequence(name, n_frames=n, width=w, height=h, seed=0)
    else:
        from mslam_ref import datasets

        if not Path(source).exists():
            raise FileNotFoundError(f"{source}: no such file or folder")
        if not hasattr(datasets, "load_sequence"):
            raise ValueError(f"{source}: dataset loaders are not available in this build")
        seq = datasets.load_sequence(str(source), calib=cal)
    if len(seq) == 0:
        raise ValueError(f"{source}: the sequence has no frames")
    first = _first_readable(seq, str(source or "synthetic"))
    H, W = first.shape
    if cal is not None:
        if (cal.width, cal.height) != (W, H):
            raise ValueError(
                f"{calib}: calibration is for {cal.width}x{cal.height} but the images are {W}x{H}"
            )
        seq.K = cal.K
    use_calib = cfg.use_calib or cal is not None
    if use_calib and seq.K is None:
        raise ValueError(
            f"{source or 'synthetic'}: calibrated mode (use_calib) but no intrinsics; "
            "pass --calib FILE (width, height, calibration: [fx, fy, cx, cy])"
        )
    prior_name = prior or ("synthetic" if synthetic else "rgbd" if seq.has_depth else None)
    if prior_name is None:
        raise ValueError(
            f"{source}: the frames have no depth, so neither the synthetic nor the rgbd prior "
            "can make pointmaps; use --prior twoview (classical two-view geometry) or --prior mast3r "
            "with your own MASt3R install and checkpoint"
        )
    if prior_name in ("synthetic", "rgbd") and not seq.has_depth:
        raise ValueError(
            f"{source}: the {prior_name} prior needs depth images; the source has none"
        )
    if prior_name == "synthetic" and (seq.T_WC is None or seq.K is None):
        raise ValueError(f"{source}: the synthetic prior needs ground-truth poses and intrinsics")
    if cfg.dataset.subsample > 1:
        seq = SubsampledSequence(seq, cfg.dataset.subsample)
    long_side = cfg.dataset.long_side
    if long_side and max(W, H) > long_side:
        w, h = round(W * long_side / max(W, H)), round(H * long_side / max(W, H))
        seq = ResizedSequence(seq, w, h, (W, H))
    if max_frames is not None and max_frames < len(seq):
        seq = _Truncated(seq, max_frames)
    p = _make_prior(prior_name, seq, use_calib)
    K = seq.K if use_calib else None
    if K is not None and hasattr(p, "network_intrinsics"):
        K = p.network_intrinsics(K, first)  # pointmaps come at the network resolution
    return Source(seq, p, prior_name, K, seq.name or str(source))


def _first_readable(seq: Any, name: str, tries: int = 10) -> Frame:
    """The first frame that loads (the size and calibration checks need one)."""
    last = None
    for i in range(min(tries, len(seq))):
        try:
            return seq[i]
        except (OSError, ValueError, cv2.error) as exc:
            last = exc
    raise ValueError(f"{name}: cannot read any of the first {min(tries, len(seq))} frames ({last})")


class _Truncated(FrameSequence):
    """The first ``n`` frames of ``base`` (``--max-frames``)."""

    def __init__(self, base: FrameSequence, n: int) -> None:
        self.base = base
        self.name, self.K, self.has_depth = base.name, base.K, base.has_depth
        self.distortion = base.distortion
        self.timestamps = np.asarray(base.timestamps)[:n]
        self.T_WC = None if base.T_WC is None else np.asarray(base.T_WC)[:n]
        for attr in ("width", "height"):
            if hasattr(base, attr):
                setattr(self, attr, getattr(base, attr))

    def _load(self, i: int) -> Frame:
        return self.base[i]
