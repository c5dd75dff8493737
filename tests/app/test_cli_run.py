"""``mslam run`` in-process: outputs exist and are well-formed; bad input fails early and cleanly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mslam.cli import main
from mslam.formats import read_ply, read_tum

SOURCE = "synthetic:loop:14:64x48"
OUTPUTS = (
    "trajectory.txt",
    "keyframes.txt",
    "reconstruction.ply",
    "summary.json",
    "trajectory.png",
)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    out = tmp_path_factory.mktemp("run") / "out"
    rc = main(["run", SOURCE, "--out", str(out), "--kernels", "fast", "--quiet"])
    assert rc == 0
    return out


def test_outputs_exist_and_are_well_formed(run_dir: Path):
    for name in OUTPUTS:
        assert (run_dir / name).is_file(), name
    assert not list(run_dir.glob(".*")), "temporary files left behind"
    assert not list(run_dir.parent.glob(".*")), "temporary folders left behind"
    s = json.loads((run_dir / "summary.json").read_text(), parse_constant=_reject_nan)
    for key in (
        "frames",
        "keyframes",
        "loop_closure_edges",
        "relocalisations",
        "skipped_frames",
        "seconds",
        "frames_per_second",
        "kernels",
        "prior",
        "ate_rmse",
        "path_length",
    ):
        assert key in s, key
    assert s["frames"] == 14 and s["kernels"] == "fast" and s["prior"] == "synthetic"
    assert s["prior_metric"] is True  # the synthetic prior declares its pointmaps metric
    assert s["skipped_frames"] == 0 and not s["interrupted"]
    ts, poses = read_tum(run_dir / "trajectory.txt")
    assert len(ts) == s["frames_with_pose"] == 14
    assert np.all(np.diff(ts) > 0) and np.allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0)
    kts, _ = read_tum(run_dir / "keyframes.txt")
    assert len(kts) == s["keyframes"] and set(kts) <= set(ts)
    xyz, rgb = read_ply(run_dir / "reconstruction.ply")
    assert xyz.dtype == np.float32 and rgb.dtype == np.uint8 and len(xyz) > 1000
    assert np.all(np.isfinite(xyz))
    # the synthetic room is about 4 m x 3 m: points stay within a few metres of the cameras
    assert np.percentile(np.linalg.norm(xyz - poses[:, :3].mean(0), axis=1), 95) < 5.0
    assert (run_dir / "trajectory.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _reject_nan(token: str) -> None:
    raise ValueError(f"summary.json: non-standard JSON constant {token}")


def _no_outputs(out: Path) -> bool:
    return not out.exists() or not any((out / n).exists() for n in OUTPUTS)


@pytest.mark.parametrize(
    "args, message",
    [
        (["synthetic:nowhere"], "unknown synthetic path"),
        (["synthetic:loop:x"], "synthetic:NAME"),
        (["/definitely/not/here"], "no such file"),
        (["--config", "/no/such/config.yaml"], "config file not found"),
        (["--set", "tracking.no_such_key=1"], "unknown config key"),
        (["--set", "tracking.Q_conf=abc"], "must be a number"),
        (["--kernels", "ref", "--max-frames", "0"], "--max-frames"),
    ],
)
def test_bad_input_exits_2_without_outputs(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    rc = main(["run", *args, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and err.count("\n") == 1
    assert _no_outputs(out)


def test_missing_calibration_fails_before_work(tmp_path, capsys, monkeypatch):
    # An image folder without intrinsics in calibrated mode: error before any frame is processed.
    import cv2

    import mslam.system as system_pkg
    from mslam import datasets

    if not hasattr(datasets, "load_sequence"):
        pytest.skip("mslam.datasets.load_sequence not available")
    img_dir = tmp_path / "imgs"
    img_dir.mkdir()
    for i in range(3):
        cv2.imwrite(str(img_dir / f"{i:03d}.png"), np.full((48, 64, 3), 50 * i, np.uint8))
    called = []
    monkeypatch.setattr(system_pkg, "run_slam", lambda *a, **k: called.append(1))
    out = tmp_path / "out"
    rc = main(["run", str(img_dir), "--out", str(out), "--config", "calib", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and not called and _no_outputs(out)
    assert "intrinsics" in err or "calib" in err or "depth" in err


def test_inconsistent_calibration_is_an_error(tmp_path, capsys):
    calib = tmp_path / "calib.yaml"
    calib.write_text("width: 640\nheight: 480\ncalibration: [500.0, 500.0, 320.0, 240.0]\n")
    out = tmp_path / "out"
    rc = main(["run", SOURCE, "--out", str(out), "--calib", str(calib), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "640x480" in err and "64x48" in err
    assert _no_outputs(out)


def test_ctrl_c_writes_what_exists(tmp_path, monkeypatch, fast64):
    from mslam.system import frontend

    calls = {"n": 0}
    original = frontend.SlamSystem.process

    def interrupt_after_five(self, frame):
        calls["n"] += 1
        if calls["n"] > 5:
            raise KeyboardInterrupt
        return original(self, frame)

    monkeypatch.setattr(frontend.SlamSystem, "process", interrupt_after_five)
    out = tmp_path / "out"
    rc = main(["run", "synthetic:loop:12:64x48", "--out", str(out), "--kernels", "fast", "--quiet"])
    assert rc == 130
    s = json.loads((out / "summary.json").read_text(), parse_constant=_reject_nan)
    assert s["interrupted"] and s["frames"] == 5
    assert len(read_tum(out / "trajectory.txt")[0]) == 5


def _break_frames(monkeypatch, bad):
    from mslam.datasets.synthetic import SyntheticSequence

    original = SyntheticSequence._load

    def broken(self, i):
        if i in bad:
            raise OSError(f"frame {i}: corrupt file")
        return original(self, i)

    monkeypatch.setattr(SyntheticSequence, "_load", broken)


def test_unreadable_frame_is_exit_2_without_outputs(tmp_path, monkeypatch, capsys):
    _break_frames(monkeypatch, (3,))
    out = tmp_path / "out"
    rc = main(["run", "synthetic:loop:6:32x24", "--out", str(out), "--kernels", "ref", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot read frame 3" in err and err.count("\n") == 1
    assert not out.exists()


def test_unreadable_frames_are_skipped_and_counted(tmp_path, monkeypatch, fast64):
    _break_frames(monkeypatch, (3, 7))
    out = tmp_path / "out"
    argv = ["run", "synthetic:loop:12:64x48", "--out", str(out), "--kernels", "fast", "--quiet"]
    with pytest.warns(RuntimeWarning, match="skipping frame"):
        rc = main([*argv, "--skip-bad-frames"])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text(), parse_constant=_reject_nan)
    assert s["skipped_frames"] == 2 and s["frames"] == 10
    assert [k["frame"] for k in s["skipped"]] == [3, 7]
    assert "2 unreadable frame(s) skipped (the first: frame 3)" in s["warnings"]


def test_config_inherit_and_overrides(tmp_path):
    from mslam.config import load_config

    child = tmp_path / "mine.yaml"
    child.write_text("inherit: calib\ntracking:\n  Q_conf: 2\nretrieval:\n  k: 5\n")
    cfg = load_config(child, ["local_opt.max_iters=4", "matching.dist_thresh=1e-2"])
    assert cfg.use_calib and cfg.dataset.subsample == 2  # from calib.yaml
    assert cfg.tracking().Q_conf == 2.0 and cfg.retrieval().k == 5  # child
    assert cfg.backend().max_iters == 4 and cfg.matching().dist_thresh == 0.01  # --set
    assert cfg.tracking().sigma_ray == 0.003  # base default
    assert cfg.fusion().filtering_mode == "weighted_pointmap"
    bad = tmp_path / "bad.yaml"
    bad.write_text("trackin:\n  Q_conf: 2\n")
    with pytest.raises(ValueError, match="unknown config key 'trackin'"):
        load_config(bad)


@pytest.mark.parametrize("config,mode", [(None, "first"), ("base", "weighted_pointmap")])
def test_rgbd_source_defaults_to_the_rgbd_config(tmp_path, fast64, config, mode):
    """A source with depth runs the RGB-D prior, and without --config its packaged config."""
    seq_dir = tmp_path / "seq"
    assert (
        main(
            [
                "synth",
                "loop",
                "--out",
                str(seq_dir),
                "--frames",
                "4",
                "--width",
                "64",
                "--height",
                "48",
            ]
        )
        == 0
    )
    out = tmp_path / "out"
    args = ["run", str(seq_dir), "--out", str(out), "--kernels", "fast", "--quiet"]
    assert main(args + (["--config", config] if config else [])) == 0
    s = json.loads((out / "summary.json").read_text(), parse_constant=_reject_nan)
    assert s["prior"] == "rgbd"
    assert s["config"]["tracking"]["filtering_mode"] == mode


def test_a_single_image_is_refused_by_the_twoview_prior(tmp_path, capsys):
    """One image has no pair, so the two-view prior can pose nothing: exit 2 before any work,
    one line, no output (the RGB-D prior poses a single frame)."""
    import cv2

    d = tmp_path / "one"
    d.mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(d / "000.png"), (rng.random((48, 64, 3)) * 255).astype(np.uint8))
    out = tmp_path / "out"
    rc = main(["run", str(d), "--prior", "twoview", "--out", str(out), "--kernels", "ref",
               "--quiet"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "needs at least 2" in err, err
    assert not out.exists()
