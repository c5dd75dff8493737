"""docs/upstream.md §10 — input sequences: frames, loaders for every supported layout, calibration files.

``load_sequence(source)`` dispatches on the source (upstream ``load_dataset`` dispatches on
path components; here on the folder's content):

================================  ==================================================
source                            loader
================================  ==================================================
``synthetic:NAME``                ``mslam_ref.synthetic.make_sequence(NAME, ...)``
video file (``.mp4``, ``.avi``…)  :class:`VideoSequence`
folder with ``frame-*.color.*``   :func:`load_7scenes`
folder with ``mav0/cam0``         :func:`load_euroc`
folder with ``rgb.txt`` /         :func:`load_tum`
``associations.txt``
folder with images                :func:`load_image_folder`
================================  ==================================================

Every loader returns a :class:`FrameSequence` (``len``, ``seq[i] -> Frame``, ``K`` or None,
``name``, ``has_depth``, ``T_WC`` ground truth or None, ``timestamps``).

Public names, in reading order:
    Frame, FrameSequence, load_sequence, subsample_sequence, Calibration, read_calibration,
    load_tum, write_tum_sequence, load_7scenes, load_euroc, load_image_folder,
    VideoSequence
"""

from __future__ import annotations

from pathlib import Path

from mslam.datasets.files import FileSequence
from mslam.datasets.folders import (
    VIDEO_SUFFIXES,
    VideoSequence,
    load_7scenes,
    load_euroc,
    load_image_folder,
)
from mslam.datasets.frame import Frame, FrameSequence
from mslam.datasets.readers import Calibration, read_calibration
from mslam.datasets.tum import load_tum, write_tum_sequence
from mslam.datasets.views import SubsampledSequence

__all__ = [
    "Calibration",
    "FileSequence",
    "Frame",
    "FrameSequence",
    "VideoSequence",
    "load_7scenes",
    "load_euroc",
    "load_image_folder",
    "load_sequence",
    "load_tum",
    "read_calibration",
    "subsample_sequence",
    "write_tum_sequence",
]


def subsample_sequence(seq: FrameSequence, step: int) -> FrameSequence:
    """Keep every ``step``-th frame (upstream ``dataset.subsample``); ``Frame.index`` restarts at 0."""
    if int(step) < 1:
        raise ValueError(f"subsample: must be >= 1, got {step}")
    if step == 1:
        return seq
    if isinstance(seq, FileSequence):
        return seq.subsampled(step)
    return SubsampledSequence(seq, step)


def load_sequence(
    source: str | Path,
    calib=None,
    subsample: int = 1,
    size: tuple[int, int] | None = None,
    **synthetic_kwargs,
) -> FrameSequence:
    """Open any supported source (see the module table).

    Args:
        source: ``synthetic:NAME``, a video file or a folder.
        calib: a calibration YAML path or :class:`Calibration` overriding the source's own
            (upstream ``--calib``); None keeps the source's (or none).
        subsample: keep every n-th frame.
        size: optional working size ``(W, H)``; frames are resized and ``K`` rescaled (file
            sources; a synthetic sequence is rendered at ``width``/``height`` instead).
        **synthetic_kwargs: ``n_frames``, ``width``, ``height``, ``seed`` for synthetic sources.

    Raises:
        FileNotFoundError: the source does not exist.
        ValueError: unknown layout or bad files, naming the path.
    """
    step = int(subsample)
    if step < 1:
        raise ValueError(f"subsample: must be >= 1, got {subsample}")
    text = str(source)
    if text.startswith("synthetic:"):
        from mslam.datasets.synthetic import make_sequence, parse_synthetic

        name, n, w, h = parse_synthetic(text)
        params = {"n_frames": n, "width": w, "height": h, "seed": 0}
        if size is not None:
            params["width"], params["height"] = size
        params.update(synthetic_kwargs)
        return subsample_sequence(make_sequence(name, **params), step)
    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if path.is_file():
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return VideoSequence(path, calib, step, size)
        raise ValueError(f"{path}: unknown input (expected a video {', '.join(VIDEO_SUFFIXES)})")
    if any(path.glob("frame-*.color.*")):
        seq = load_7scenes(path, calib, size)
    elif (path / "mav0" / "cam0").is_dir() or (path / "cam0" / "data.csv").is_file():
        seq = load_euroc(path, calib, size)
    elif (path / "rgb.txt").is_file() or (path / "associations.txt").is_file():
        seq = load_tum(path, calib, size)
    elif any(p.suffix.lower() in (".png", ".jpg", ".jpeg") for p in path.iterdir()):
        seq = load_image_folder(path, calib, size)
    else:
        raise ValueError(
            f"{path}: unknown layout (expected rgb.txt, mav0/cam0/data.csv, frame-*.color.*, "
            "or *.png/*.jpg images)"
        )
    return subsample_sequence(seq, step)
