"""The frame loop (upstream main.py's ``__main__``): every frame of a source through the system.

Public names, in reading order:
    FrameObserver, run_slam
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
import warnings
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from types import FrameType
from typing import Any, Protocol

import cv2

from mslam.config import SlamConfig
from mslam.datasets.frame import Frame, check_frame_size
from mslam.kernels import KernelSet
from mslam.priors.base import is_metric
from mslam.system.frontend import SlamSystem
from mslam.system.sources import Source, self_calibrate
from mslam.system.state import FrameStatus, Mode

__all__ = ["FrameObserver", "run_slam"]


class FrameObserver(Protocol):
    """Something that looks at the system after every frame (a live recording)."""

    def after_frame(self, i: int, frame: Frame, system: SlamSystem, status: FrameStatus) -> None:
        """Called after frame ``i`` was processed with its status."""
        ...


def run_slam(
    source: Source,
    cfg: SlamConfig,
    kernels: KernelSet,
    progress: bool = False,
    system: SlamSystem | None = None,
    skip_bad_frames: bool = False,
    observer: FrameObserver | None = None,
) -> tuple[SlamSystem, dict[str, Any]]:
    """Run the SLAM loop over every frame of ``source``.

    Upstream: main.py ``__main__`` (the frame loop) with ``single_thread: True``.

    Reliability: a frame that cannot be read (``OSError``, ``ValueError``, ``cv2.error``) is a
    ``ValueError`` naming the frame, or with ``skip_bad_frames`` is skipped with a warning and
    counted (``stats.skipped_frames``, ``meta["skipped"]``); a sequence whose tracking never
    recovers simply ends with what it had. Ctrl-C (SIGINT, in the main thread) stops at the
    next frame boundary and returns what exists (``meta["interrupted"]``); a second Ctrl-C
    raises ``KeyboardInterrupt`` at once.

    Args:
        source: from :func:`open_source`.
        cfg: the resolved configuration.
        kernels: the kernel set.
        progress: show progress on stderr (:func:`mslam.system.progress.progress_bar`).
        system: continue an existing system (default: a new one).
        skip_bad_frames: skip unreadable frames instead of raising.
        observer: called as ``observer.after_frame(i, frame, system, status)`` after every
            processed frame (``mslam.export.observer.SystemTap``: the Rerun recording), or None.

    Returns:
        the system (keyframes, graph, per-frame poses, stats) and ``meta`` (source, prior,
        seconds, interrupted; ``focal_estimate`` when the focal length was estimated;
        ``depth_scale_assumed`` when the depth's units are only its layout's convention).
    """
    focal = None
    t_focal = time.perf_counter()
    if system is None:
        focal = self_calibrate(source)  # uncalibrated two-view: f and the lens from the video
        system = SlamSystem(source.prior, cfg, kernels, source.K)
    t_focal = time.perf_counter() - t_focal
    seq = source.sequence  # undistorted where the pre-pass found the lens
    n = len(seq)
    bar = None
    if progress:
        from mslam.system.progress import progress_bar

        bar = progress_bar(n)  # a tqdm bar on a terminal, sparse whole lines in a log
    interrupted = False
    shape = None
    skipped: list[dict[str, Any]] = []
    frames = _ReadAhead(seq, source.prior)
    t0 = time.perf_counter()
    try:
        with _sigint_at_frame_boundary() as stop:
            for i in range(n):
                if stop.is_set():
                    interrupted = True
                    break
                try:
                    frame = frames.get(i)
                    shape = shape or frame.shape
                    check_frame_size(frame.shape, shape)
                except (OSError, ValueError, cv2.error) as exc:
                    if not skip_bad_frames:
                        raise ValueError(
                            f"{source.name}: cannot read frame {i}: {exc} "
                            "(--skip-bad-frames skips such frames)"
                        ) from None
                    _skip(system, skipped, source.name, i, exc)
                else:
                    frames.prefetch(i + 1, system.pair_partner())  # beside frame i's work
                    status = system.process(frame)
                    if observer is not None:
                        observer.after_frame(i, frame, system, status)
                    if bar is not None:
                        bar.set_postfix(kf=len(system.keyframes), mode=system.mode.name,
                                        last=status, refresh=False)  # fmt: skip
                if bar is not None:
                    bar.update(1)
    except _HardStop:
        raise
    except KeyboardInterrupt:
        interrupted = True
    finally:
        frames.close()
        if bar is not None:
            bar.close()
    system.close()  # the background backend (if any) finishes its queued keyframes
    seconds = time.perf_counter() - t0 + t_focal  # the focal pre-pass counts too
    system.mode = Mode.TERMINATED
    meta = {
        "source": source.name,
        "prior": source.prior_name,
        "prior_metric": is_metric(source.prior),
        "seconds": seconds,
        "interrupted": interrupted,
        "skipped": skipped,
    }
    if focal is not None:
        meta["focal_estimate"] = {**focal, "seconds": t_focal}
    if source.depth_scale_assumed is not None:
        meta["depth_scale_assumed"] = source.depth_scale_assumed
    return system, meta


def _skip(
    system: SlamSystem, skipped: list[dict[str, Any]], name: str, i: int, exc: BaseException
) -> None:
    system.stats.skipped_frames += 1
    skipped.append({"frame": i, "reason": str(exc)})
    warnings.warn(f"{name}: skipping frame {i}: {exc}", RuntimeWarning, stacklevel=3)


class _ReadAhead:
    """Frame ``i + 1`` is read on one worker thread while frame ``i`` is processed.

    Decoding and resizing (OpenCV) release the GIL, so the read of the next frame overlaps the
    current frame's work instead of adding to it. Only the worker reads the sequence, in
    order, one frame at a time, so a reader with state (a video capture, a render cache) sees
    the same calls as a plain loop; a read's exception is raised when that frame's turn comes.
    With a prior that prefetches (``TwoViewPrior.prefetching``, on by default;
    ``RGBDPrior.prefetching``, off), :meth:`prefetch` also hands frame ``i + 1`` and its likely
    partner to ``prior.prefetch`` before frame ``i`` is processed, whose worker thread does that
    frame's own work (and the two-view prior the pair's flow) while frame ``i`` is tracked.
    """

    def __init__(self, seq: Any, prior: Any) -> None:
        self.seq, self.prior = seq, prior
        self.on = bool(getattr(prior, "prefetching", False))
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mslam-read")
        self.pending: dict[int, Future[Frame]] = {}

    def __enter__(self) -> _ReadAhead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _submit(self, i: int) -> None:
        if i < len(self.seq) and i not in self.pending:
            self.pending[i] = self.pool.submit(self.seq.__getitem__, i)

    def get(self, i: int) -> Frame:
        """Frame ``i`` (read now unless it was read ahead); starts reading frame ``i + 1``."""
        self._submit(i)
        fut = self.pending.pop(i)
        try:
            return fut.result()
        finally:
            self._submit(i + 1)

    def prefetch(self, i: int, partner: Frame | None) -> None:
        """Hand frame ``i`` to the prior's prefetch (when the prior prefetches), with the frame
        it will most likely be paired with (``SlamSystem.pair_partner``)."""
        if not self.on or i >= len(self.seq):
            return
        self._submit(i)
        try:
            frame = self.pending[i].result()
        except (OSError, ValueError, cv2.error):
            return  # raised by get(i) in its turn
        self.prior.prefetch(frame, partner)

    def close(self) -> None:
        """Wait for the prior's worker and the reader: no thread outlives the run."""
        try:
            if self.on:
                self.prior.join_prefetch()
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)


class _HardStop(KeyboardInterrupt):
    """A second Ctrl-C: stop now, write nothing."""


@contextlib.contextmanager
def _sigint_at_frame_boundary() -> Iterator[threading.Event]:
    """First SIGINT sets the yielded event (checked between frames); a second one raises
    ``KeyboardInterrupt`` (no output). Outside the main thread the handler cannot be installed."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            raise _HardStop
        stop.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)
