"""Bad inputs end with one line naming the file/key/value, exit 2, before the work.

Sources by explicit scheme, configuration ranges, degenerate alignments in ``eval``, BAL/g2o
readers (docs/reliability.md).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mslam.cli import main

RUN = ["--kernels", "ref", "--quiet"]


def one_line_error(capsys, rc: int, expected: str) -> str:
    err = capsys.readouterr().err
    assert rc == 2, err
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_folder_named_synthetic_is_a_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(["run", "synthetic_kitchen", "--out", "out", *RUN])
    one_line_error(capsys, rc, "synthetic_kitchen: no such file or folder")
    (tmp_path / "synthetic_kitchen").mkdir()
    rc = main(["run", "synthetic_kitchen", "--out", "out", *RUN])
    err = capsys.readouterr().err
    assert rc == 2 and "synthetic_kitchen" in err and "unknown synthetic path" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "override, key",
    [
        ("tracking.Q_conf=.nan", "tracking.Q_conf"),
        ("tracking.huber=0", "tracking.huber"),
        ("matching.max_iter=0", "matching.max_iter"),
        ("dataset.long_side=8", "dataset.long_side"),
        ("dataset.long_side=-1", "dataset.long_side"),
        ("dataset.subsample=1.5", "dataset.subsample"),
        ("local_opt.sigma_ray=.inf", "local_opt.sigma_ray"),
        ("retrieval.k=0", "retrieval.k"),
    ],
)
def test_config_values_outside_their_range(tmp_path, capsys, override, key):
    rc = main(["run", "--out", str(tmp_path / "o"), "--set", override, *RUN])
    err = one_line_error(capsys, rc, f"--set {override}: {key} must be")
    assert "base.yaml" not in err
    assert not (tmp_path / "o").exists()


def test_config_file_value_names_the_file(tmp_path):
    from mslam.config import load_config

    bad = tmp_path / "mine.yaml"
    bad.write_text("inherit: base\ntracking:\n  huber: -1.0\n")
    with pytest.raises(ValueError, match=r"mine.yaml: tracking.huber must be .*\(0, inf\)"):
        load_config(bad)


def test_every_numeric_base_key_has_a_stated_range():
    from mslam.config_ranges import RANGES
    from mslam.config_yaml import CONFIG_DIR, read_yaml

    base = read_yaml(CONFIG_DIR / "base.yaml")
    numeric = {
        f"{s}.{k}"
        for s, sec in base.items()
        if isinstance(sec, dict)
        for k, v in sec.items()
        if isinstance(v, int | float) and not isinstance(v, bool)
    }
    assert numeric == set(RANGES)


@pytest.mark.parametrize("which", ["config", "calib"])
def test_yaml_errors_are_one_line(tmp_path, capsys, which):
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracking:\n  Q_conf: [1,\n  huber: 2\n")
    flag = "--config" if which == "config" else "--calib"
    rc = main(["run", "--out", str(tmp_path / "o"), flag, str(bad), *RUN])
    one_line_error(capsys, rc, "bad.yaml: line")


def _traj(path, stamps, P):
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(P), 1))
    rows = np.column_stack([stamps, P, q])
    path.write_text("".join(" ".join(f"{v:.17g}" for v in r) + "\n" for r in rows))
    return str(path)


_GOOD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 1], [2, 1, 0.5]], float)


@pytest.mark.parametrize(
    "case, expected",
    [
        ("equal_stamps", "timestamps are equal"),
        ("huge", "large"),
        ("collinear", "degenerate"),
        ("static", "degenerate"),
    ],
)
def test_eval_refuses_degenerate_alignments(tmp_path, capsys, case, expected):
    t = np.arange(5.0)
    gt = _traj(tmp_path / "gt.txt", t, _GOOD * (1e300 if case == "huge" else 1.0))
    est = {
        "equal_stamps": lambda: _traj(tmp_path / "e.txt", np.zeros(5), _GOOD),
        "huge": lambda: _traj(tmp_path / "e.txt", t, (_GOOD + np.eye(5, 3)) * 1e300),
        "collinear": lambda: _traj(tmp_path / "e.txt", t, np.outer(t, [1.0, 2.0, 3.0])),
        "static": lambda: _traj(tmp_path / "e.txt", t, np.full((5, 3), 7.0)),
    }[case]()
    one_line_error(capsys, main(["eval", gt, est]), expected)


def test_eval_alignment_is_scale_invariant(tmp_path, capsys):
    """Relative tests: the same shape at 1e-200 or 1e300 aligns like at 1 (an absolute
    threshold would give scale 0).

    The library aligns any finite scale; the command refuses coordinates beyond
    ``MAX_ABS_COORDINATE`` (no camera path is a million kilometres long)."""
    from mslam.commands.eval import MAX_ABS_COORDINATE
    from mslam.evaluate import ate

    t = np.arange(5.0)
    gt = _traj(tmp_path / "gt.txt", t, _GOOD)
    for k in (1e-200, 1.0, MAX_ABS_COORDINATE / 2):
        assert main(["eval", gt, _traj(tmp_path / "e.txt", t, _GOOD * k)]) == 0
        res = json.loads(capsys.readouterr().out)
        assert res["ate_rmse"] < 1e-9 and res["scale"] == pytest.approx(1 / k)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (5, 1))
    res = ate(t, np.column_stack([_GOOD * 1e300, q]), t, np.column_stack([_GOOD, q]), "sim3")
    assert res.rmse < 1e-9 and res.scale == pytest.approx(1e-300)


@pytest.mark.parametrize("which", ["estimate", "reference"])
def test_eval_refuses_absurd_coordinates(tmp_path, capsys, which):
    t = np.arange(5.0)
    good = _traj(tmp_path / "good.txt", t, _GOOD)
    huge = _traj(tmp_path / "huge.txt", t, _GOOD + np.array([0.0, 1e300, 0.0]))
    args = [good, huge] if which == "estimate" else [huge, good]
    one_line_error(capsys, main(["eval", *args]), "huge.txt: pose 1 has coordinate y = 1e+300")


def _bal_text() -> str:
    from mslam import bal as io
    from mslam_ref.ba import synthetic

    problem, _ = synthetic.make_bal_problem(n_cams=3, n_points=10)
    return io.format_bal(problem)


def test_bal_header_with_fewer_observations(tmp_path):
    from mslam import bal as io

    lines = _bal_text().splitlines()
    M, P, O = (int(x) for x in lines[0].split())
    lines[0] = f"{M} {P} {O - 2}"
    path = tmp_path / "p.txt"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"p.txt:\d+: more values than the header"):
        io.read_bal(path)


@pytest.mark.parametrize("tail", ["0.5\n", "1 2 3\n", "\n\nextra\n"])
def test_bal_trailing_data(tmp_path, tail):
    from mslam import bal as io

    path = tmp_path / "p.txt"
    path.write_text(_bal_text() + tail)
    with pytest.raises(ValueError, match="trailing data"):
        io.read_bal(path)


@pytest.mark.parametrize("where", ["obs", "param"])
def test_bal_non_finite_names_the_line(tmp_path, where):
    from mslam import bal as io

    lines = _bal_text().splitlines()
    O = int(lines[0].split()[2])
    k = 2 if where == "obs" else O + 5  # 0-based: an observation, a camera parameter
    tok = lines[k].split()
    tok[-1] = "nan"
    lines[k] = " ".join(tok)
    path = tmp_path / "p.txt"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=rf"p.txt:{k + 1}: "):
        io.read_bal(path)


def test_bal_writer_refuses_non_finite():
    from mslam import bal as io
    from mslam_ref.ba import synthetic

    problem, _ = synthetic.make_bal_problem(n_cams=3, n_points=10)
    problem.points[0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        io.format_bal(problem)


def test_g2o_zero_quaternion_names_the_line(tmp_path):
    from mslam import bal as io

    path = tmp_path / "g.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match=r"g.g2o:2: quaternion of zero length"):
        io.read_g2o_se3(path)


def test_baseline_without_depth_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    import mslam.system as system_pkg
    from mslam.system import sources

    class NoDepth:
        has_depth = False

    real = sources.open_source

    def open_without_depth(*a, **k):
        src = real(*a, **k)
        src.sequence = NoDepth()
        return src

    calls = []
    monkeypatch.setattr(system_pkg, "open_source", open_without_depth)
    monkeypatch.setattr(system_pkg, "run_slam", lambda *a, **k: calls.append(1))
    rc = main(["run", "synthetic:loop:4:32x24", "--out", str(tmp_path / "o"), "--baseline", *RUN])
    one_line_error(capsys, rc, "--baseline")
    assert not calls and not (tmp_path / "o").exists()


def test_calibration_size_mismatch_is_named_as_such(tmp_path, capsys):
    seq = tmp_path / "seq"
    assert main(["synth", "loop", "--out", str(seq), "--frames", "2", "--width", "32",
                 "--height", "24"]) == 0  # fmt: skip
    capsys.readouterr()
    calib = tmp_path / "c.yaml"
    calib.write_text("width: 64\nheight: 48\ncalibration: [50.0, 50.0, 32.0, 24.0]\n")
    rc = main(["run", str(seq), "--out", str(tmp_path / "o"), "--calib", str(calib), *RUN])
    err = one_line_error(capsys, rc, "does not match the calibration 64x48")
    assert err.startswith("mslam run: error: --calib:") and "cannot read" not in err


def test_folder_calibration_size_mismatch_names_the_folder(tmp_path, capsys):
    seq = tmp_path / "seq"
    assert main(["synth", "loop", "--out", str(seq), "--frames", "2", "--width", "32",
                 "--height", "24"]) == 0  # fmt: skip
    capsys.readouterr()
    (seq / "calib.yaml").write_text(
        "width: 64\nheight: 48\ncalibration: [50.0, 50.0, 32.0, 24.0]\n"
    )
    rc = main(["run", str(seq), "--out", str(tmp_path / "o"), "--prior", "twoview", *RUN])
    err = one_line_error(capsys, rc, "does not match the calibration 64x48")
    assert err.startswith(f"mslam run: error: {seq}: the folder's calibration file:")
    assert "--calib" not in err


def test_nan_translation_in_ground_truth_is_named(tmp_path):
    from mslam.formats import read_tum

    path = tmp_path / "groundtruth.txt"
    path.write_text("# t tx ty tz qx qy qz qw\n0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"groundtruth.txt:3: non-finite tx"):
        read_tum(path)
