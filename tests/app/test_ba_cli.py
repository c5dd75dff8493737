"""``mslam ba``: JSON output, --out round trip, user errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mslam import bal as io
from mslam import cli
from mslam_ref.ba import synthetic


def test_cli_ba_json_and_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p, _ = synthetic.make_bal_problem(n_cams=4, n_points=20, seed=3)
    f = tmp_path / "p.txt"
    io.write_bal(p, f)
    out = tmp_path / "o.bal"
    assert cli.main(["ba", str(f), "--iterations", "5", "--out", str(out)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["final_cost"] < rep["initial_cost"]
    assert 1 <= rep["iterations"] <= 5 and rep["seconds"] > 0.0
    assert set(rep["profile"]) >= {"schur_complement", "build_system"}
    q = io.read_bal(out)
    assert q.cameras.shape == p.cameras.shape


def test_cli_ba_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["ba", str(tmp_path / "missing.txt")]) == 2
    bad = tmp_path / "bad.txt"
    bad.write_text("1 1\n")
    assert cli.main(["ba", str(bad)]) == 2
    assert "bad.txt:1:" in capsys.readouterr().err


def test_cli_ba_g2o(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from mslam.g2o_ba import read_g2o_ba, write_g2o_ba

    p, _ = synthetic.make_pinhole_problem(n_cams=4, n_points=20, stereo_fraction=0.4, seed=4)
    f = tmp_path / "p.g2o"
    write_g2o_ba(p, {"poses": list(range(4)), "points": list(range(4, 24))}, f)
    out = tmp_path / "o.g2o"
    argv = ["ba", str(f), "--robust", "huber", "--damping", "identity", "--out", str(out)]
    assert cli.main([*argv, "--iterations", "5"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["cameras"] == 4 and rep["observations"] == len(p.obs_cam)
    assert rep["final_cost"] < rep["initial_cost"]
    assert rep["profile"]["symbolic_decomposition"] > 0.0
    q, _ = read_g2o_ba(out)
    assert not (q.poses == p.poses).all()
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE3:EXPMAP 1 0 0 0\n")
    assert cli.main(["ba", str(bad)]) == 2
    assert "bad.g2o:1:" in capsys.readouterr().err
