"""``mslam eval`` run in-process through ``mslam.cli.main``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mslam import formats as io
from mslam.cli import main
from mslam_ref import sim3


@pytest.fixture
def traj_pair(tmp_path):
    """A ground truth and a Sim(3)-transformed, slightly noisy estimate with offset stamps."""
    rng = np.random.default_rng(0)
    n = 50
    xi = np.zeros((n, 7))
    xi[:, :3] = np.cumsum(rng.normal(0, 0.2, (n, 3)), axis=0)
    xi[:, 3:6] = rng.normal(0, 0.3, (n, 3))
    gt = sim3.exp(xi)
    gt[:, :3], gt[:, 7] = xi[:, :3], 1.0
    G = sim3.exp(np.array([0.3, -1.0, 2.0, 0.1, 0.2, -0.3, np.log(2.0)]))
    est = sim3.mul(G[None], gt)
    est[:, :3] += rng.normal(0, 1e-3, (n, 3))
    stamps = 100.0 + 0.1 * np.arange(n)
    io.write_tum(tmp_path / "gt.txt", stamps, gt)
    io.write_tum(tmp_path / "est.txt", stamps[::2] + 0.004, est[::2])  # keyframes, 4 ms late
    return tmp_path / "est.txt", tmp_path / "gt.txt"


def _run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_eval_prints_json(capsys, traj_pair) -> None:
    est, gt = traj_pair
    code, out, err = _run(capsys, ["eval", str(gt), str(est)])
    assert code == 0, err
    res = json.loads(out)
    assert res["matched"] == 25 and res["n_est"] == 25 and res["align"] == "sim3"
    assert res["scale"] == pytest.approx(0.5, rel=1e-2)
    assert 0 < res["ate_rmse"] < 3e-3
    assert res["ate_mean"] <= res["ate_rmse"] <= res["ate_max"]
    assert 0 <= res["ate_median"] <= res["ate_max"]


def test_eval_align_and_max_diff_options(capsys, traj_pair) -> None:
    est, gt = traj_pair
    _, out, _ = _run(capsys, ["eval", str(gt), str(est), "--align", "se3"])
    se3 = json.loads(out)
    assert se3["scale"] == 1.0 and se3["ate_rmse"] > 0.1
    code, _, err = _run(capsys, ["eval", str(gt), str(est), "--max-diff", "0.001"])
    assert code == 2 and "no estimate stamp" in err and len(err.strip().splitlines()) == 1


def test_eval_missing_file_exit_code_2(capsys, traj_pair, tmp_path) -> None:
    est, _ = traj_pair
    missing = tmp_path / "nope.txt"
    code, out, err = _run(capsys, ["eval", str(missing), str(est)])
    assert code == 2 and out == ""
    assert str(missing) in err and len(err.strip().splitlines()) == 1


def test_eval_malformed_file_names_file_and_line(capsys, traj_pair, tmp_path) -> None:
    _, gt = traj_pair
    bad = tmp_path / "bad.txt"
    bad.write_text("0 0 0 0 0 0 0 1\n1 0 0 zero 0 0 0 1\n")
    code, out, err = _run(capsys, ["eval", str(gt), str(bad)])
    assert code == 2 and out == ""
    assert f"{bad}:2:" in err


def test_eval_kitti_needs_kitti(capsys, traj_pair, tmp_path) -> None:
    _, gt = traj_pair
    M = sim3.to_matrix(np.tile(sim3.identity(), (3, 1)))
    kitti = tmp_path / "k.txt"
    kitti.write_text("".join(" ".join(map(str, m[:3].ravel())) + "\n" for m in M))
    code, _, err = _run(capsys, ["eval", str(gt), str(kitti)])
    assert code == 2 and "KITTI" in err


@pytest.mark.parametrize(
    ("est", "gt", "align", "rmse", "matched"),
    [
        ("freiburg1_xyz-ORB_kf_mono.txt", "freiburg1_xyz-groundtruth.txt", "sim3", 0.009755, 32),
        ("V102.txt", "V102_groundtruth.csv", "sim3", 0.083841, 798),
        ("KITTI_00_ORB.txt", "KITTI_00_gt.txt", "se3", 1.303450, 4541),
    ],
)
def test_eval_reproduces_evo_on_shared_data(capsys, shared_data, est, gt, align, rmse, matched):
    d = shared_data / "traj"
    code, out, err = _run(capsys, ["eval", str(d / gt), str(d / est), "--align", align])
    assert code == 0, err
    res = json.loads(out)
    assert res["matched"] == matched
    assert res["ate_rmse"] == pytest.approx(rmse, abs=1e-6)


def test_eval_takes_the_reference_first_as_evo(capsys, traj_pair) -> None:
    """evo_ape REF EST: swapping the files changes the result (the estimate drives the
    association and its scale is fitted), so the order is part of the interface."""
    est, gt = traj_pair
    _, out, _ = _run(capsys, ["eval", str(gt), str(est)])
    _, out_swapped, _ = _run(capsys, ["eval", str(est), str(gt)])
    res, swapped = json.loads(out), json.loads(out_swapped)
    assert res["n_est"] == 25 and swapped["n_est"] == 50
    assert res["scale"] == pytest.approx(0.5, rel=1e-2)
    assert swapped["scale"] == pytest.approx(2.0, rel=1e-2)
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    usage = capsys.readouterr().out
    assert "REFERENCE ESTIMATE" in usage and "FIRST" in usage
