"""The device switch: ``--device cpu|cuda`` on ``mslam run`` and ``mslam ba``, no silent fallback."""

from __future__ import annotations

import json

import pytest

from mslam.cli import main
from mslam.device import cuda_driver_present, use_device

NO_GPU = pytest.mark.skipif(cuda_driver_present(), reason="an NVIDIA driver is present here")


@pytest.mark.parametrize("command", ["run", "ba"])
def test_device_is_in_the_help(command: str, capsys) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    out = capsys.readouterr().out
    assert "--device" in out and "cuda" in out


@NO_GPU
def test_cuda_without_a_gpu_is_one_line_and_writes_nothing(tmp_path, capsys) -> None:
    out = tmp_path / "out"
    rc = main(["run", "synthetic:loop:4:32x24", "--out", str(out), "--device", "cuda", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--device cuda" in err
    assert list(tmp_path.iterdir()) == []


@NO_GPU
def test_ba_on_cuda_without_a_gpu_is_refused(tmp_path, capsys) -> None:
    problem = tmp_path / "p.txt"
    problem.write_text("1 1 1\n0 0 1.0 2.0\n" + "0\n" * 9 + "0\n0\n1\n")
    rc = main(["ba", str(problem), "--kernels", "fast", "--device", "cuda"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--device cuda" in err


def test_cuda_with_the_reference_kernels_is_refused() -> None:
    with pytest.raises(ValueError, match="ref kernels are NumPy"):
        use_device("cuda", "ref")
    with pytest.raises(ValueError, match="unknown device"):
        use_device("tpu", "fast")


def test_a_cpu_run_says_so_in_its_summary(tmp_path) -> None:
    out = tmp_path / "out"
    assert (
        main(["run", "synthetic:loop:6:32x24", "--out", str(out), "--kernels", "ref", "--quiet"])
        == 0
    )
    s = json.loads((out / "summary.json").read_text())
    assert s["device"] == "cpu"
    assert s["config"]["local_opt"]["use_cuda"] is False
    assert s["config"]["mast3r_prior"]["device"] == "cpu"  # the network follows the switch
