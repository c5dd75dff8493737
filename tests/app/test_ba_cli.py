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
