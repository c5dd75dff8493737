"""Outputs are whole or absent; faults end with one line and the documented exit code.

docs/reliability.md lists which fault each test holds.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mslam.cli import main

SRC = "synthetic:loop:6:32x24"
RUN = ["--kernels", "ref", "--quiet"]
OUTPUTS = {
    "trajectory.txt",
    "keyframes.txt",
    "keyframes",  # the keyframe images
    "reconstruction.ply",
    "summary.json",
    "trajectory.png",
}


def strict_json(path: Path) -> dict:
    """summary.json read with a parser that rejects NaN and Infinity."""

    def reject(token: str) -> None:
        raise ValueError(f"{path}: non-standard JSON constant {token}")

    return json.loads(path.read_text(), parse_constant=reject)


def one_line_error(capsys, rc: int, expected: str) -> str:
    err = capsys.readouterr().err
    assert rc == 2, err
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err, err
    return err


def whole_set_or_nothing(out: Path) -> None:
    """The target is absent, or holds exactly one complete, consistent output set."""
    if not out.exists():
        return
    assert {p.name for p in out.iterdir()} == OUTPUTS
    s = strict_json(out / "summary.json")
    n = len((out / "trajectory.txt").read_text().splitlines())
    assert n == s["frames_with_pose"]
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}")]


def test_unalignable_ground_truth_still_writes_outputs(tmp_path):
    out = tmp_path / "out"
    assert main(["run", "synthetic:rotation:6:32x24", "--out", str(out), *RUN]) == 0
    s = strict_json(out / "summary.json")
    assert {p.name for p in out.iterdir()} == OUTPUTS
    assert "degenerate" in s["evaluation_error"] and "ate" not in s


def test_existing_output_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    one_line_error(capsys, main(["run", SRC, "--out", str(out), *RUN]), "--overwrite")
    assert (out / "mine.txt").read_text() == "keep me"
    assert main(["run", SRC, "--out", str(out), *RUN, "--overwrite"]) == 0
    whole_set_or_nothing(out)


def test_empty_existing_folder_is_filled(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    assert main(["run", SRC, "--out", str(out), *RUN]) == 0
    whole_set_or_nothing(out)


@pytest.mark.parametrize("cmd", ["run", "synth", "ba"])
def test_out_below_a_regular_file(tmp_path, capsys, cmd):
    (tmp_path / "file").write_text("x")
    out = str(tmp_path / "file" / "out")
    argv = {
        "run": ["run", SRC, "--out", out, *RUN],
        "synth": [
            "synth",
            "loop",
            "--out",
            out,
            "--frames",
            "2",
            "--width",
            "16",
            "--height",
            "16",
        ],
        "ba": ["ba", str(_bal(tmp_path)), "--out", out],
    }[cmd]
    one_line_error(capsys, main(argv), "is a file, not a folder")


def _bal(tmp_path: Path) -> Path:
    from mslam import bal as io
    from mslam_ref.ba import synthetic

    problem, _ = synthetic.make_bal_problem(n_cams=3, n_points=10)
    path = tmp_path / "problem.txt"
    io.write_bal(problem, path)
    return path


def test_ba_out_folder_and_existing_file(tmp_path, capsys):
    bal = _bal(tmp_path)
    one_line_error(capsys, main(["ba", str(bal), "--out", str(tmp_path)]), "is a folder")
    target = tmp_path / "solved.txt"
    target.write_text("old")
    one_line_error(capsys, main(["ba", str(bal), "--out", str(target)]), "--overwrite")
    assert main(["ba", str(bal), "--out", str(target), "--overwrite", "--iterations", "2"]) == 0
    assert target.read_text().split()[:3] == bal.read_text().split()[:3]


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores folder permissions")
def test_synth_into_read_only_parent(tmp_path, capsys):
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        rc = main(["synth", "loop", "--out", str(parent / "seq"), "--frames", "2"])
        one_line_error(capsys, rc, "not writable")
    finally:
        parent.chmod(0o755)


def test_read_only_parent_found_by_the_check(tmp_path, monkeypatch, capsys):
    """The same fault where root cannot be denied a write: os.access says no."""
    real = os.access
    parent = tmp_path / "ro"
    parent.mkdir()
    monkeypatch.setattr(os, "access", lambda p, m: False if Path(p) == parent else real(p, m))
    rc = main(["synth", "loop", "--out", str(parent / "seq"), "--frames", "2"])
    one_line_error(capsys, rc, "not writable")
    assert not (parent / "seq").exists()


@pytest.mark.parametrize("cmd", ["run", "synth"])
def test_full_disk_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, capsys, cmd):
    import mslam.formats as mio
    from mslam.datasets import tum

    def full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(mio, "write_ply", full)
    monkeypatch.setattr(tum, "calibration_yaml", full)
    out = tmp_path / "out"
    argv = {
        "run": ["run", SRC, "--out", str(out), *RUN],
        "synth": [
            "synth",
            "loop",
            "--out",
            str(out),
            "--frames",
            "2",
            "--width",
            "16",
            "--height",
            "16",
        ],
    }[cmd]
    one_line_error(capsys, main(argv), "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_ba_full_disk(tmp_path, monkeypatch, capsys):
    from mslam import atomic

    def full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    bal = _bal(tmp_path)
    monkeypatch.setattr(atomic, "_write", full)
    rc = main(["ba", str(bal), "--out", str(tmp_path / "solved.txt"), "--iterations", "1"])
    one_line_error(capsys, rc, "No space left on device")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["problem.txt"]


def test_sigkill_during_ba_out_leaves_no_temporary_file(tmp_path):
    bal, out = _bal(tmp_path), tmp_path / "solved.txt"
    code = (
        "import os, signal, sys\n"
        "import mslam.atomic as atomic\n"
        "def killed(path, data):\n"
        "    open(path, 'w').close()\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        "atomic._write = killed\n"
        "from mslam.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    argv = ["ba", str(bal), "--out", str(out), "--iterations", "1"]
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and len(list(tmp_path.iterdir())) == 2  # the 0-byte temporary file
    assert main(argv) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["problem.txt", "solved.txt"]


def test_out_that_holds_the_source_or_the_cwd_is_refused(tmp_path, monkeypatch, capsys):
    seq = tmp_path / "seq"
    argv = ["synth", "loop", "--out", str(seq), "--frames", "2", "--width", "16", "--height", "16"]
    assert main(argv) == 0
    capsys.readouterr()
    rc = main(["run", str(seq / "rgb"), "--out", str(seq), "--overwrite", *RUN])
    one_line_error(capsys, rc, "contains SOURCE")
    monkeypatch.chdir(seq)
    one_line_error(capsys, main(["run", SRC, "--out", ".", "--overwrite", *RUN]), "current folder")
    assert (seq / "rgb.txt").is_file()


@pytest.mark.parametrize(
    "source", ["synthetic:loop:10:100000x100000", "synthetic:loop:20000000:32x24"]
)
def test_synthetic_size_caps(tmp_path, capsys, source):
    one_line_error(capsys, main(["run", source, "--out", str(tmp_path / "o"), *RUN]), "cap")


def test_synth_size_cap(tmp_path, capsys):
    argv = ["synth", "loop", "--out", str(tmp_path / "o"), "--frames", "20000000"]
    one_line_error(capsys, main(argv), "frames must be in")


def test_eval_into_a_closed_pipe_is_quiet(tmp_path, monkeypatch, capsys):
    traj = tmp_path / "t.txt"
    traj.write_text("".join(f"{i} {i} {i * i % 3} {i % 2} 0 0 0 1\n" for i in range(6)))
    r, w = os.pipe()
    os.close(r)
    stdout = os.fdopen(w, "w")
    monkeypatch.setattr(sys, "stdout", stdout)
    try:
        assert main(["eval", str(traj), str(traj)]) == 0
    finally:
        stdout.close()
    assert capsys.readouterr().err == ""


def test_ctrl_c_stops_at_a_frame_boundary(tmp_path, monkeypatch):
    from mslam.system import frontend

    calls = {"n": 0}
    original = frontend.SlamSystem.process

    def sigint_in_frame_three(self, frame):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return original(self, frame)

    monkeypatch.setattr(frontend.SlamSystem, "process", sigint_in_frame_three)
    out = tmp_path / "out"
    assert main(["run", "synthetic:loop:8:32x24", "--out", str(out), *RUN]) == 130
    s = strict_json(out / "summary.json")
    assert s["interrupted"] and s["frames"] == 3  # frame 3 finished, frame 4 never started
    whole_set_or_nothing(out)


def test_second_ctrl_c_leaves_nothing(tmp_path, monkeypatch):
    from mslam.system import frontend

    def two_sigints(self, frame):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        return "never"

    monkeypatch.setattr(frontend.SlamSystem, "process", two_sigints)
    out = tmp_path / "out"
    assert main(["run", SRC, "--out", str(out), *RUN]) == 130
    assert list(tmp_path.iterdir()) == []


_KILLER = """
import os, signal, sys
import mslam.atomic as a
n = {"k": 0}
def arm(mod, name):
    f = getattr(mod, name)
    def wrapped(*a, **k):
        n["k"] += 1
        if n["k"] == int(sys.argv[1]):
            os.kill(os.getpid(), signal.SIGKILL)
        return f(*a, **k)
    setattr(mod, name, wrapped)
arm(a, "write_atomic")  # before any writer imports it
import mslam.outdir as od
import mslam.formats as mio
from mslam.datasets import tum
arm(mio, "write_tum"); arm(mio, "write_ply"); arm(od, "_move_into_place")
arm(tum, "encode_png")
from mslam.cli import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("kill_at", [1, 2, 3, 4, 5, 6, 99])
def test_sigkill_mid_write_leaves_nothing_or_one_whole_set(tmp_path, kill_at):
    out = tmp_path / "out"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    argv = [sys.executable, "-c", _KILLER, str(kill_at), "run", SRC, "--out", str(out), *RUN]
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    if kill_at == 99:
        assert proc.returncode == 0, proc.stderr
        whole_set_or_nothing(out)
        assert out.exists()
        return
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert not out.exists()
    if kill_at != 4:
        return
    # the next run removes the killed run's temporary folder and succeeds
    assert subprocess.run([*argv[:2], "99", *argv[4:]], env=env, timeout=300).returncode == 0
    whole_set_or_nothing(out)


@pytest.mark.parametrize("kill_at", [1, 3, 7])
def test_sigkill_during_synth_leaves_nothing(tmp_path, kill_at):
    out = tmp_path / "seq"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    synth = ["synth", "loop", "--out", str(out), "--frames", "3", "--width", "16", "--height", "16"]
    proc = subprocess.run([sys.executable, "-c", _KILLER, str(kill_at), *synth], env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert not out.exists()
    assert main(synth) == 0  # and the killed run's temporary files go with the next run
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]
