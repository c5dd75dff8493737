"""``mslam.run`` — the SLAM system on a sequence from Python, with the command line's behaviour.

``mslam run SOURCE --out DIR [options]`` is this function with a summary printed afterwards:
the same checks before any work (one clear ``ValueError`` each), the same choice of the
packaged config by prior (``rgbd`` and ``twoview`` sources get their own working resolution),
the same device switch, the same atomic output set::

    import mslam

    result = mslam.run("synthetic:loop:40:96x72", out="runs/x", prior="synthetic")
    result.summary["ate_rmse"], result.summary["frames_posed_fraction"]
    indices, timestamps, T_WC = result.trajectory   # every posed frame, Sim(3) (M, 8)

Config keys are set with keyword arguments whose ``__`` stands for the dot of
``--set SECTION.KEY=VALUE``: ``mslam.run(src, dataset__long_side=256)``.

Public names, in reading order:
    RunResult, run
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mslam.errors import UserError
from mslam.export import ExportRequest
from mslam.system import SlamSystem, Source

__all__ = ["RunResult", "run"]

#: Longest image side the RGB-D prior may run at without asking (a whole frame costs ~0.2 s at
#: 160x120 and ~0.8 s at 512x384 on 2 cores, benchmarks/RESULTS.md; more at the full size).
RGBD_MAX_AUTO_SIDE = 320


@dataclass
class RunResult:
    """What a run gives back.

    Attributes:
        summary: the dict written to ``summary.json`` (counts, timings, health, ATE).
        system: the SLAM system (keyframes, graph, per-frame poses, stats).
        source: the opened input (sequence, prior, intrinsics).
        out: the output folder, or None when nothing was written.
        interrupted: Ctrl-C stopped the run early (the outputs hold the frames processed).
    """

    summary: dict[str, Any]
    system: SlamSystem
    source: Source
    out: Path | None
    interrupted: bool

    @property
    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame indices (M,), timestamps (M,) and Sim(3) poses T_WC (M, 8) of the posed frames."""
        return self.system.frame_poses()


def _settings(settings: list[str] | None, overrides: dict[str, Any], device: str) -> list[str]:
    """``--set`` strings from a list and from keyword arguments (``a__b=v`` -> ``a.b=v``)."""
    out = list(settings or [])
    for key, value in overrides.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        out.append(f"{key.replace('__', '.')}={text}")
    # One switch: the kernels' arch and the network's torch device.
    out += [f"local_opt.use_cuda={str(device == 'cuda').lower()}", f"mast3r_prior.device={device}"]
    return out


def _check_resolution(source: Source, long_side: int) -> None:
    """Refuse, before any work, to run the RGB-D prior at full resolution by accident."""
    if source.prior_name != "rgbd" or long_side:
        return
    H, W = source.sequence[0].shape
    if max(H, W) > RGBD_MAX_AUTO_SIDE:
        raise UserError(
            f"this config runs the RGB-D prior at the full {W}x{H} (dataset.long_side = 0), "
            "about a second per frame on 2 CPU cores; add --set dataset.long_side=160 (the rgbd "
            "config's working size), use --config rgbd_512 (the paper's 512 px), or "
            f"--set dataset.long_side={max(H, W)} to insist"
        )


def run(
    source: str | Path | None = None,
    out: str | Path | None = None,
    *,
    config: str | Path | None = None,
    prior: str | None = None,
    calib: str | Path | None = None,
    kernels: str = "fast",
    precision: str = "f64",
    device: str = "cpu",
    max_frames: int | None = None,
    settings: list[str] | None = None,
    overwrite: bool = False,
    progress: bool = False,
    skip_bad_frames: bool = False,
    baseline: bool = False,
    exports: ExportRequest | None = None,
    **overrides: Any,
) -> RunResult:
    """Run the SLAM system on ``source`` and (with ``out``) write the output set.

    Args:
        source: ``synthetic:NAME[:FRAMES[:WxH]]``, a TUM/7-Scenes folder, an image folder or a
            video file; None is the built-in synthetic loop.
        out: the output folder (trajectory.txt, keyframes.txt, reconstruction.ply,
            summary.json, trajectory.png, keyframes/); None writes nothing.
        config: a YAML config or a packaged name (``base``, ``calib``, ``rgbd``, ``twoview``,
            ...); default: base, or the prior's own for ``rgbd`` and ``twoview``.
        prior: ``synthetic``, ``rgbd``, ``mast3r`` or ``twoview``; default by the source.
        calib: an intrinsics YAML; turns on calibrated mode.
        kernels: ``fast`` (Taichi) or ``ref`` (NumPy).
        precision: ``f64`` or ``f32`` (fast kernels).
        device: ``cpu`` or ``cuda`` (refused without an NVIDIA GPU).
        max_frames: process at most this many frames.
        settings: ``SECTION.KEY=VALUE`` strings, as ``--set``.
        overwrite: replace a non-empty ``out``.
        progress: a progress bar on stderr.
        skip_bad_frames: skip unreadable frames instead of raising.
        baseline: also run OpenCV's RGB-D odometry (needs depth).
        exports: Rerun / COLMAP / depth outputs (``mslam.export.ExportRequest``).
        **overrides: config keys, ``SECTION__KEY=VALUE``.

    Returns:
        a :class:`RunResult`.

    Raises:
        ValueError: bad input, found before any frame is processed (nothing is written).
    """
    from mslam.config import config_to_dict, load_config
    from mslam.device import use_device
    from mslam.kernels import load_kernels
    from mslam.outdir import check_target, staged_folder
    from mslam.system import open_source, run_slam, write_outputs

    target = None if out is None else check_target(out, overwrite)
    if source and target is not None and Path(source).resolve().is_relative_to(target.resolve()):
        raise UserError(f"--out {target}: contains SOURCE {source}; choose another folder")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"--max-frames: must be >= 1, got {max_frames}")
    use_device(device, kernels, precision)  # before any work: no silent fallback
    keys = _settings(settings, overrides, device)
    name = None if source is None else str(source)
    cfg = load_config(config, keys)
    src = open_source(name, cfg, calib, prior, max_frames)
    if config is None and src.prior_name in ("rgbd", "twoview"):
        # The prior's packaged default (configs/rgbd.yaml, configs/twoview.yaml, docs/system.md):
        # its working resolution and tracking keys differ from base.yaml; open the source again.
        cfg = load_config(src.prior_name, keys)
        src = open_source(name, cfg, calib, prior, max_frames)
    _check_resolution(src, cfg.dataset.long_side)
    if calib is not None and not cfg.use_calib:
        cfg = replace(cfg, use_calib=True)  # upstream: --calib forces use_calib
    kernel_set = load_kernels(kernels)
    if baseline and not src.sequence.has_depth:
        raise UserError(f"--baseline: {src.name} has no depth images (the RGB-D odometry "
                        "baseline needs them)")  # fmt: skip
    exports = exports or ExportRequest(Path(".") if target is None else target)
    with exports.recording(src.K if cfg.use_calib else None) as tap:
        system, meta = run_slam(src, cfg, kernel_set, progress=progress,
                                skip_bad_frames=skip_bad_frames, observer=tap)  # fmt: skip
        if baseline and not meta["interrupted"]:
            from mslam.baselines import rgbd_odometry_ate

            meta["baseline"] = rgbd_odometry_ate(src.sequence)
        meta["config"] = config_to_dict(cfg)
        meta["device"] = device
        registration = getattr(src.sequence, "colour_registration", None)  # 7-Scenes folders
        if registration:
            meta["colour_registration"] = registration
        if target is None:
            from mslam.system.outputs import evaluate_run, summary_dict

            summary = summary_dict(system, meta, evaluate_run(system, src.sequence))
        else:
            with staged_folder(target, overwrite) as tmp:
                summary = write_outputs(tmp, system, src.sequence, meta)
                exports.write(tmp, system, src.sequence)
    return RunResult(summary, system, src, target, bool(meta["interrupted"]))
