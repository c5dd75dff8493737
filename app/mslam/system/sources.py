"""docs/upstream.md §10 — opening a SOURCE for ``mslam run``: sequence, calibration and prior, checked first.

``open_source`` resolves everything a run needs *before any work starts*, so that a bad path,
a missing or inconsistent calibration, or a prior that cannot work on the source is one clear
error (``ValueError``/``FileNotFoundError``) and no output is written:

* SOURCE → ``mslam.datasets.load_sequence``, the one loader of every input: ``None`` is the
  built-in synthetic ``loop`` (``mslam.datasets.synthetic.DEFAULT_SYNTHETIC``),
  ``synthetic:NAME[:FRAMES[:WxH]]`` a rendered scene, anything else a path (TUM-layout
  folder, 7-Scenes folder, EuRoC folder, image folder, video file); a folder is a folder
  whatever its name.
* ``--calib FILE`` (upstream: forces ``use_calib``) sets the intrinsics; its ``width``/``height``
  must match the images. ``use_calib`` without any intrinsics is an error.
* Prior: ``synthetic`` for synthetic sources, ``rgbd`` when the frames carry depth, otherwise
  ``mast3r`` or ``twoview`` (RGB only: the depth files of the source are never read; K only
  when calibrated) must be asked for explicitly; a depth-less source without one is an error.
* ``dataset.long_side`` shrinks frames (never enlarges) so the long side has that many pixels,
  with the intrinsics rescaled; ``dataset.subsample`` keeps every n-th frame.

``self_calibrate`` (called by ``run_slam`` before the first frame): an uncalibrated two-view
run takes its focal length from the video where the video determines it
(``mslam.priors.twoview_focal``).

Public names, in reading order:
    PRIORS, Source, open_source, self_calibrate
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mslam.config import SlamConfig
from mslam.datasets import load_sequence
from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.views import ResizedSequence, SubsampledSequence, TruncatedSequence
from mslam.priors.base import Prior

__all__ = ["PRIORS", "Source", "open_source", "self_calibrate"]

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
        depth_scale_assumed: the depth's raw units per metre when a depth prior reads depth
            whose scale is only its layout's convention (``FileSequence.depth_scale_assumed``),
            else None.
    """

    sequence: FrameSequence
    prior: Prior
    prior_name: str
    K: np.ndarray | None
    name: str
    depth_scale_assumed: float | None = None


def _make_prior(
    name: str, sequence: Any, use_calib: bool = False, cfg: SlamConfig | None = None
) -> Prior:
    if name == "twoview":
        from mslam.priors.twoview import TwoViewPrior, TwoViewPriorConfig

        tv = cfg.twoview_prior() if cfg is not None else TwoViewPriorConfig()
        if not use_calib:
            return TwoViewPrior(cfg=tv)  # the focal guess until self_calibrate
        H, W = _first_readable(sequence, sequence.name or "source").shape
        return TwoViewPrior(sequence.K, (W, H), tv)
    if name == "synthetic":
        from mslam.priors.synthetic import SyntheticPrior

        return SyntheticPrior(sequence)
    if name == "rgbd":
        from mslam.priors import rgbd

        return rgbd.RGBDPrior(
            sequence, cfg.rgbd_prior() if cfg is not None else rgbd.RGBDPriorConfig()
        )
    from mslam.priors import mast3r

    return mast3r.load_prior(cfg=cfg.mast3r_prior() if cfg is not None else None)


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
        from mslam.datasets.readers import read_calibration

        cal = read_calibration(calib)
    synthetic = source is None or str(source).startswith("synthetic:")
    seq: Any = load_sequence(str(source or "synthetic:"), calib=cal)
    if len(seq) == 0:
        raise ValueError(f"{source}: the sequence has no frames")
    calib_from = "--calib" if cal else f"{source}: the folder's calibration file"
    first = _first_readable(seq, str(source or "synthetic"), calib_from)
    H, W = first.shape
    if cal is not None:
        if (cal.width, cal.height) != (W, H):
            raise ValueError(
                f"{calib}: calibration is for {cal.width}x{cal.height} but the images are {W}x{H}"
            )
        if synthetic or seq.K is None:
            # The file loaders apply --calib themselves: with distortion terms the frames are
            # undistorted into the new camera matrix (K_opt), which is the one the run must use.
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
            "can make pointmaps; use --prior twoview (classical two-view geometry) or --prior "
            "mast3r with your own MASt3R install and checkpoint"
        )
    if prior_name in ("synthetic", "rgbd") and not seq.has_depth:
        raise ValueError(
            f"{source}: the {prior_name} prior needs depth images; the source has none: use "
            "--prior twoview (RGB only, classical two-view geometry) or --prior mast3r"
        )
    if prior_name == "synthetic" and (seq.T_WC is None or seq.K is None):
        raise ValueError(f"{source}: the synthetic prior needs ground-truth poses and intrinsics")
    if (use_calib or prior_name == "rgbd") and hasattr(seq, "register_colour"):
        seq.register_colour()  # colour not registered to depth (7-Scenes folders)
    assumed = None
    if prior_name in ("synthetic", "rgbd") and getattr(seq, "depth_scale_assumed", False):
        assumed = float(seq.depth_scale)
    if prior_name == "twoview" and getattr(seq, "depth_paths", None) is not None:
        seq.depth_paths, seq.has_depth = None, False  # RGB only: no depth file is ever read
    if cfg.dataset.subsample > 1:
        seq = SubsampledSequence(seq, cfg.dataset.subsample)
    long_side = cfg.dataset.long_side
    if long_side and max(W, H) > long_side:
        w, h = round(W * long_side / max(W, H)), round(H * long_side / max(W, H))
        seq = ResizedSequence(seq, w, h, (W, H))
    if max_frames is not None and max_frames < len(seq):
        seq = TruncatedSequence(seq, max_frames)
    if prior_name == "twoview" and len(seq) < 2:
        raise ValueError(
            f"{source}: 1 frame to run; the twoview prior makes pointmaps from pairs of frames, "
            "so it needs at least 2"
        )
    p = _make_prior(prior_name, seq, use_calib, cfg)
    K = seq.K if use_calib else None
    if K is not None and hasattr(p, "network_intrinsics"):
        K = p.network_intrinsics(K, first)  # pointmaps come at the network resolution
    return Source(seq, p, prior_name, K, seq.name or str(source), assumed)


def self_calibrate(source: Source) -> dict[str, object] | None:
    """Set an uncalibrated two-view prior's focal length from the video (module docstring),
    and undistort the source's frames where the video shows radial distortion clearly
    (``source.sequence`` becomes a ``DivisionUndistortedSequence``); returns the estimate's
    record for ``summary.json`` (``focal_estimate``), or None for other priors, calibrated
    runs and a prior that already has one."""
    from mslam.datasets.views import DivisionUndistortedSequence
    from mslam.priors.twoview import TwoViewPrior
    from mslam.priors.twoview_focal import estimate_focal
    from mslam.priors.twoview_geometry import focal_guess_intrinsics
    from mslam.priors.twoview_selfcal import estimate_camera

    prior = source.prior
    if not isinstance(prior, TwoViewPrior) or prior.K is not None or prior.focal_scale != 1.0:
        return None
    if not prior.cfg.self_calibrate:
        return None
    camera = estimate_camera(source.sequence) if prior.cfg.camera_from_views else None
    if camera is not None and camera.used:
        prior.focal_scale = camera.focal_scale
        if camera.lam:
            source.sequence = DivisionUndistortedSequence(source.sequence, camera.lam)
        H, W = _first_readable(source.sequence, source.name).shape
        return camera.record(float(focal_guess_intrinsics(W, H)[0, 0]))
    estimate = estimate_focal(source.sequence)
    prior.focal_scale = estimate.scale
    if estimate.lens is not None and estimate.lens.lam_in_use:
        source.sequence = DivisionUndistortedSequence(source.sequence, estimate.lens.lam_in_use)
    return {**estimate.as_dict(), "many_views": camera and camera.as_dict()}


def _first_readable(seq: Any, name: str, calib_from: str = "--calib", tries: int = 10) -> Frame:
    """The first frame that loads (the size and calibration checks need one); a calibration
    that does not fit the images is reported as such, not as unreadable frames, naming where
    it came from (``calib_from``: the option or the source folder's own file)."""
    from mslam.datasets.files import CalibrationMismatch

    first = None
    for i in range(min(tries, len(seq))):
        try:
            return seq[i]
        except CalibrationMismatch as exc:
            raise ValueError(f"{calib_from}: {exc}") from None
        except (OSError, ValueError, cv2.error) as exc:
            first = first or exc
    n = min(tries, len(seq))
    raise ValueError(f"{name}: none of the first {n} frames can be read (frame 0: {first})")
