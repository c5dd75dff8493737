"""``mslam.run``: the Python entry point behaves like ``mslam run`` (checks, config, outputs)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import mslam
from mslam.cli import main

SRC = "synthetic:loop:10:48x36"


def test_run_without_out_writes_nothing_and_returns_the_summary(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    result = mslam.run(SRC, kernels="ref")
    assert result.out is None and list(tmp_path.iterdir()) == []
    idx, _ts, T = result.trajectory
    assert result.summary["frames"] == 10 and result.summary["frames_with_pose"] == len(idx)
    assert T.shape == (len(idx), 8) and np.all(np.isfinite(T))
    assert result.summary["device"] == "cpu" and not result.interrupted


def test_run_writes_what_the_command_writes(tmp_path) -> None:
    api = mslam.run(SRC, tmp_path / "api", kernels="ref", tracking__Q_conf=1.5)
    assert main(["run", SRC, "--out", str(tmp_path / "cli"), "--kernels", "ref", "--quiet",
                 "--set", "tracking.Q_conf=1.5"]) == 0  # fmt: skip
    for name in ("trajectory.txt", "keyframes.txt", "reconstruction.ply"):
        assert (tmp_path / "api" / name).read_bytes() == (tmp_path / "cli" / name).read_bytes()
    written = json.loads((tmp_path / "api" / "summary.json").read_text())
    assert written["config"]["tracking"]["Q_conf"] == 1.5
    assert written["keyframes"] == api.summary["keyframes"]
    assert set(written) == set(api.summary)


def test_keyword_settings_are_config_keys(tmp_path) -> None:
    result = mslam.run("synthetic:loop:4:64x48", kernels="ref", dataset__long_side=32)
    assert result.summary["resolution"] == [32, 24]
    with pytest.raises(ValueError, match="Qconf"):
        mslam.run(SRC, kernels="ref", tracking__Qconf=1.0)


def test_bad_input_is_refused_before_any_work(tmp_path) -> None:
    with pytest.raises(ValueError, match="max-frames"):
        mslam.run(SRC, tmp_path / "o", max_frames=0)
    with pytest.raises(ValueError, match="--device"):
        mslam.run(SRC, tmp_path / "o", device="tpu")
    assert list(tmp_path.iterdir()) == []


def test_the_7scenes_clip_runs_as_on_the_command_line(shared_data, tmp_path, fast64) -> None:
    clip = shared_data / "seq" / "7scenes_redkitchen_f000000-000149"
    result = mslam.run(clip, max_frames=12)
    assert result.source.prior_name == "rgbd"
    assert main(["run", str(clip), "--out", str(tmp_path / "cli"), "--max-frames", "12",
                 "--quiet"]) == 0  # fmt: skip
    cli = json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert result.summary["resolution"] == cli["resolution"] == [160, 120]
    from mslam.formats import read_tum

    _, T_cli = read_tum(tmp_path / "cli" / "trajectory.txt")
    _, _, T = result.trajectory
    assert np.array_equal(T_cli[:, :3], T[:, :3].astype(T_cli.dtype))
