"""Ground truth that misses some frames (motion capture that starts late, a gap in it).

A folder whose ``groundtruth.txt`` has no pose near some frames' timestamps is read with
``T_WC = None`` (no pose for every frame) and ``T_WC_partial`` (NaN rows for the missing ones);
``FrameSequence.ground_truth`` lists the frames that have one, views keep them, and the run's
summary, ``mslam eval`` on the folder and the baseline odometry are evaluated on those frames
instead of not at all.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tolerances import F64_IDENTITY

from mslam.cli import main
from mslam.datasets import load_sequence

FRAMES = 24
MISSING = {0, 1, 2, 3, 12, 13}  # motion capture starts at frame 4 and drops frames 12-13


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("partial") / "loop"
    args = ["synth", "loop", "--out", str(out), "--frames", str(FRAMES)]
    assert main([*args, "--width", "64", "--height", "48"]) == 0
    gt = out / "groundtruth.txt"
    rows = [r for r in gt.read_text().splitlines() if r and not r.startswith("#")]
    assert len(rows) == FRAMES
    gt.write_text("\n".join(r for i, r in enumerate(rows) if i not in MISSING) + "\n")
    return out


def test_the_frames_with_ground_truth_are_listed(folder: Path) -> None:
    seq = load_sequence(folder)
    assert seq.T_WC is None and not seq.has_ground_truth
    truth = seq.ground_truth()
    assert truth is not None
    idx, ts, T = truth
    assert set(idx.tolist()) == set(range(FRAMES)) - MISSING
    np.testing.assert_allclose(ts, seq.timestamps[idx], atol=F64_IDENTITY)
    for i, T_i in zip(idx, T, strict=True):
        np.testing.assert_allclose(T_i, seq[int(i)].T_WC, atol=F64_IDENTITY)
    every2 = load_sequence(folder, subsample=2).ground_truth()
    assert every2 is not None
    assert set(every2[0].tolist()) == {i // 2 for i in set(range(0, FRAMES, 2)) - MISSING}


def test_a_run_is_evaluated_on_the_frames_with_ground_truth(folder: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["run", str(folder), "--out", str(out), "--quiet", "--baseline"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_with_pose"] == FRAMES
    assert s["ate"]["matched"] == FRAMES - len(MISSING) and s["ate_rmse"] is not None
    assert "ate_by_map" not in s  # one map: the ATE above is the map's
    assert s["baseline"]["ate"]["matched"] <= FRAMES - len(MISSING)
    traj = str(out / "trajectory.txt")
    assert main(["eval", str(folder), traj]) == 0


def test_eval_refuses_a_folder_without_any_ground_truth(folder: Path, tmp_path: Path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("rgb.txt", "depth.txt", "associations.txt", "calib.yaml"):
        if (folder / name).is_file():
            (bare / name).write_text((folder / name).read_text())
    (bare / "rgb").symlink_to(folder / "rgb")
    (bare / "depth").symlink_to(folder / "depth")
    assert main(["eval", str(bare), str(folder / "groundtruth.txt")]) == 2
    assert "no ground-truth pose for any frame" in capsys.readouterr().err
