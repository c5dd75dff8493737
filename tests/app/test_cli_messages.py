"""What ``mslam run`` tells the user: progress in a log, the plausibility line, plot units, hints.

Progress written to a pipe or file is whole lines (no carriage-return redraws); the summary
says what the plausibility checks covered; an RGB-only run's top view is in arbitrary units;
a misspelt config key gets the closest key; the rgbd prior on RGB-only frames names twoview;
an RGB-D run on depth of assumed units says so.
"""

from __future__ import annotations

import io

import cv2
import pytest

from mslam.cli import main
from mslam.datasets.synthetic import make_sequence
from mslam.system.progress import LOG_LINES, LineProgress, progress_bar


@pytest.fixture(scope="module")
def rgb_folder(tmp_path_factory):
    """Six RGB-only frames (no depth, no ground truth) of the forward path, 128x96."""
    seq = make_sequence("forward", n_frames=12, width=128, height=96, seed=0)
    folder = tmp_path_factory.mktemp("rgb") / "images"
    folder.mkdir()
    for i in range(0, 12, 2):
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.cvtColor(seq[i].rgb, cv2.COLOR_RGB2BGR))
    return folder


@pytest.fixture(scope="module")
def twoview_run(rgb_folder, tmp_path_factory):
    """An RGB-only twoview run with progress and summary on a captured (non-terminal) stderr;
    records the axis labels of trajectory.png."""
    import matplotlib.axes

    out = tmp_path_factory.mktemp("twoview") / "out"
    labels: list[str] = []
    err = io.StringIO()
    mp = pytest.MonkeyPatch()
    original = matplotlib.axes.Axes.set_xlabel
    mp.setattr(
        matplotlib.axes.Axes,
        "set_xlabel",
        lambda ax, text, *a, **k: (labels.append(text), original(ax, text, *a, **k))[1],
    )
    mp.setattr("sys.stderr", err)
    try:
        rc = main(["run", str(rgb_folder), "--out", str(out), "--prior", "twoview",
                   "--kernels", "ref"])  # fmt: skip
    finally:
        mp.undo()
    assert rc == 0, err.getvalue()
    return err.getvalue(), labels


def test_progress_in_a_log_is_sparse_whole_lines(twoview_run):
    err, _ = twoview_run
    assert "\r" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("frame ")]
    assert lines and lines[-1].startswith("frame 6/6 (100%)"), err
    assert len(lines) <= LOG_LINES + 1


@pytest.mark.parametrize("total", [1, 7, 1000, 1003])
def test_line_progress_prints_at_most_log_lines_plus_the_end(total):
    buf = io.StringIO()
    bar = LineProgress(total, buf)
    for _ in range(total):
        bar.set_postfix(kf=1, refresh=False)
        bar.update(1)
    bar.close()
    lines = buf.getvalue().splitlines()
    assert 1 <= len(lines) <= LOG_LINES + 1, lines
    assert lines[-1].startswith(f"frame {total}/{total} (100%)") and lines[-1].endswith("kf=1")
    done = [int(ln.split()[1].split("/")[0]) for ln in lines]
    assert done == sorted(set(done))


def test_progress_bar_is_tqdm_on_a_terminal_only():
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert isinstance(progress_bar(5, io.StringIO()), LineProgress)
    assert not isinstance(progress_bar(5, Tty()), LineProgress)


def test_rgb_only_plot_is_in_arbitrary_units(twoview_run):
    _, labels = twoview_run
    assert labels and all("[arbitrary units]" in t for t in labels), labels


def test_plausible_line_says_what_was_not_checked(twoview_run):
    err, _ = twoview_run
    line = next(ln for ln in err.splitlines() if "plausible" in ln)
    assert "no ground truth" in line and "scale and accuracy not checked" in line, line


def test_plausible_line_names_the_checks_that_ran():
    from mslam.commands.run import _checked

    with_gt = {"ate_rmse": 0.01, "prior": "rgbd", "prior_metric": True}
    assert _checked(with_gt) == "posed fraction and aligned scale within limits"
    assert "scale not checked: the twoview prior is not metric" in _checked(
        {**with_gt, "prior": "twoview", "prior_metric": False}
    )
    assert "no ground truth" in _checked({"prior": "rgbd", "prior_metric": True})


def test_a_caution_is_printed_and_keeps_the_plausible_line(tmp_path, capsys):
    from mslam.commands.run import _print_summary

    s = {"source": "x", "prior": "twoview", "prior_metric": False, "kernels": "fast",
         "calibrated": False, "frames": 10, "frames_with_pose": 10, "frames_posed_fraction": 1.0,
         "lost_frames": 0, "skipped_frames": 0, "lost_spans": [], "relocalised_at": [],
         "relocalisations": 0, "reloc_attempts": 0, "keyframes": 9, "edges": 8,
         "loop_closure_edges": 0, "seconds": 1.0, "frames_per_second": 10.0, "warnings": [],
         "cautions": ["the map's scale moved (at frame 7): ..."]}  # fmt: skip
    _print_summary(s, tmp_path)
    err = capsys.readouterr().err
    assert "  caution: the map's scale moved (at frame 7)" in err
    assert "plausible: no warning" in err and "WARNING" not in err


@pytest.mark.parametrize(
    "key, suggestion",
    [("tracking.Qconf", "tracking.Q_conf"), ("trackin.Q_conf", "tracking.Q_conf")],
)
def test_misspelt_config_key_gets_a_suggestion(tmp_path, capsys, key, suggestion):
    rc = main(["run", "--out", str(tmp_path / "o"), "--set", f"{key}=2", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert f"unknown config key {key!r}; did you mean {suggestion}?" in err
    assert not (tmp_path / "o").exists()


def test_misspelt_section_in_a_file_gets_a_suggestion(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("trackin:\n  Q_conf: 2\n")
    rc = main(["run", "--out", str(tmp_path / "o"), "--config", str(bad), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "'trackin'; did you mean tracking?" in err, err


def test_unrelated_key_gets_no_suggestion(tmp_path, capsys):
    rc = main(["run", "--out", str(tmp_path / "o"), "--set", "tracking.zzz=2", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "unknown config key 'tracking.zzz'" in err and "did you mean" not in err


def test_rgbd_prior_on_rgb_frames_names_twoview(rgb_folder, tmp_path, capsys):
    rc = main(["run", str(rgb_folder), "--out", str(tmp_path / "o"), "--prior", "rgbd"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "needs depth images" in err and "--prior twoview" in err
    assert not (tmp_path / "o").exists()


def test_twoview_on_one_frame_is_refused_in_one_line(rgb_folder, tmp_path, capsys):
    rc = main(["run", str(rgb_folder), "--out", str(tmp_path / "o"), "--prior", "twoview",
               "--max-frames", "1"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "1 frame to run" in err and "at least 2" in err
    assert not (tmp_path / "o").exists()


def test_summary_says_what_the_edge_counts_are(tmp_path, capsys):
    """The console names what counts as a loop-closure edge: every non-consecutive edge that
    retrieval proposed and the check accepted, not only the closures of a loop."""
    from mslam.cli import main

    out = tmp_path / "o"
    assert main(["run", "synthetic:loop:8:32x24", "--out", str(out), "--kernels", "ref"]) == 0
    err = capsys.readouterr().err
    assert "between non-consecutive keyframes found by retrieval" in err


def test_plausible_line_says_when_the_ate_was_refused():
    from mslam.commands.run import _checked

    refused = {"prior": "twoview", "evaluation_error": "ATE not computed: a static camera"}
    assert "ATE not computed" in _checked(refused) and "no ground truth" not in _checked(refused)
    assert "no ground truth" in _checked({"prior": "twoview"})


def test_an_assumed_depth_scale_is_in_the_summary_and_on_the_console(tmp_path, capsys):
    """An RGB-D run on a TUM-layout folder whose calibration has no ``depth_scale`` records the
    5000 units per metre it assumed; with ``depth_scale`` in ``--calib`` nothing is assumed."""
    import json

    src = tmp_path / "camera"
    assert main(["synth", "loop", "--out", str(src), "--frames", "6", "--width", "64",
                 "--height", "48"]) == 0  # fmt: skip
    stated = (src / "calib.yaml").read_text()
    (src / "calib.yaml").write_text(
        "".join(ln for ln in stated.splitlines(True) if "depth_scale" not in ln)
    )
    capsys.readouterr()
    assert main(["run", str(src), "--out", str(tmp_path / "a"), "--kernels", "ref"]) == 0
    err = capsys.readouterr().err
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["depth_scale_assumed"] == 5000
    assert "depth: 5000 raw units per metre assumed" in err and "depth_scale: 1000" in err, err
    cal = tmp_path / "cal.yaml"
    cal.write_text(stated)
    assert main(["run", str(src), "--out", str(tmp_path / "b"), "--kernels", "ref", "--calib",
                 str(cal)]) == 0  # fmt: skip
    assert "depth_scale_assumed" not in json.loads((tmp_path / "b" / "summary.json").read_text())
    assert "raw units per metre assumed" not in capsys.readouterr().err


def test_too_few_posed_frames_for_an_ate_are_said_so(tmp_path, capsys):
    """Ground truth but fewer than 3 posed frames: the summary and the console say why there is
    no ATE, and the plausibility line does not claim there is no ground truth."""
    import json

    out = tmp_path / "two"
    assert main(["run", "synthetic:loop:6:64x48", "--max-frames", "2", "--kernels", "ref",
                 "--out", str(out)]) == 0  # fmt: skip
    err = capsys.readouterr().err
    s = json.loads((out / "summary.json").read_text())
    why, posed = s["evaluation_error"], s["frames_with_pose"]
    assert posed < 3 and why == f"ATE not computed: too few posed frames ({posed}; 3 needed)"
    assert "ate_rmse" not in s
    assert f"  {why}" in err and "no ground truth" not in err, err
