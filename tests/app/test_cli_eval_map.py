"""``mslam eval --map`` (dense-map metrics) run in-process through ``mslam.cli.main``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tolerances import MAP_PLY_ATOL

from mslam import formats as io
from mslam.cli import main
from mslam.datasets import load_sequence
from mslam.datasets.synthetic import make_sequence
from mslam.datasets.tum import write_tum_sequence
from mslam.map_metrics import truth_from_rgbd
from mslam_ref import sim3

#: The Sim(3) that moves the "estimate" away from the ground truth's frame.
G = np.array([0.3, -1.0, 2.0, *sim3.exp(np.array([0, 0, 0, 0.1, 0.2, -0.3, 0]))[3:7], 2.0])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A TUM folder with depth and ground truth, a Sim(3)-moved trajectory and its map."""
    root = tmp_path_factory.mktemp("scene")
    write_tum_sequence(make_sequence("loop", 12, 32, 24, seed=0), root / "seq")
    seq = load_sequence(root / "seq")
    truth = truth_from_rgbd(seq)
    io.write_tum(root / "est.txt", seq.timestamps, sim3.mul(G[None], seq.T_WC))
    io.write_ply(root / "map.ply", sim3.act(G, truth), np.zeros((len(truth), 3), np.uint8))
    io.write_ply(root / "truth.ply", truth, np.zeros((len(truth), 3), np.uint8))
    return root


def _run(capsys, argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_map_against_rgbd_folder_and_cloud(capsys, scene) -> None:
    seq = scene / "seq"
    base = ["eval", seq, scene / "est.txt", "--map", scene / "map.ply"]
    for truth in (["--truth-rgbd", seq], ["--truth-cloud", scene / "truth.ply"]):
        code, out, err = _run(capsys, [*base, *truth])
        assert code == 0, err
        res = json.loads(out)
        assert res["scale"] == pytest.approx(0.5) and res["ate_rmse"] < MAP_PLY_ATOL
        m = res["map"]
        assert m["accuracy"] < MAP_PLY_ATOL and m["completion"] < MAP_PLY_ATOL
        assert m["far"] == 0.0 and m["n_map"] == m["n_truth"]
        assert "note" not in err  # positions and orientations agree on the alignment
    code, out, err = _run(capsys, [*base, "--truth-rgbd", seq, "--map-poses"])
    assert code == 0, err
    res = json.loads(out)  # an exact Sim(3) copy: positions and orientations agree
    assert res["map"]["accuracy"] < MAP_PLY_ATOL and res["map_alignment"]["refine"] == "poses"
    code, out, _ = _run(capsys, [*base, "--truth-rgbd", seq, "--align", "se3"])
    assert code == 0 and json.loads(out)["map"]["accuracy"] > 0.1  # scale 2 left in the map


def test_map_options_bad_input(capsys, scene, tmp_path) -> None:
    seq, est, ply = scene / "seq", scene / "est.txt", scene / "map.ply"
    bad_ply = tmp_path / "bad.ply"
    bad_ply.write_text("not a ply\n")
    cases = [
        (["--map", ply], "--truth-cloud PLY or --truth-rgbd"),
        (["--truth-rgbd", seq], "--map PLY"),
        (["--map-icp"], "--map PLY"),
        (["--map-poses"], "--map PLY"),
        (["--map", ply, "--truth-rgbd", seq, "--map-icp", "--map-poses"], "choose one"),
        (["--map", tmp_path / "nope.ply", "--truth-rgbd", seq], "nope.ply: no such file"),
        (["--map", bad_ply, "--truth-rgbd", seq], "not a PLY file"),
        (["--map", ply, "--truth-cloud", bad_ply], "not a PLY file"),
        (["--map", ply, "--truth-rgbd", tmp_path / "none"], "no such folder"),
    ]
    for extra, message in cases:
        code, out, err = _run(capsys, ["eval", seq, est, *extra])
        assert code == 2 and out == "", extra
        assert message in err and len(err.strip().splitlines()) == 1, err
    with pytest.raises(SystemExit) as exc:  # argparse: the two truths exclude each other
        main(["eval", str(seq), str(est), "--map", str(ply), "--truth-cloud", str(ply),
              "--truth-rgbd", str(seq)])  # fmt: skip
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err


def test_a_rotation_the_path_leaves_free_is_noted(capsys, tmp_path) -> None:
    # Cameras on a gentle arc whose map and orientations are turned 5° (their positions are
    # not): the position fit cannot see the turn, so the metrics under it measure the turn; the
    # command says so on stderr (one line, JSON untouched) unless the map is registered.
    n = 20
    xi = np.zeros((n, 7))
    xi[:, 0] = np.linspace(0, 1, n)
    xi[:, 1] = 0.1 * np.sin(np.linspace(0, np.pi, n))
    gt = sim3.exp(xi)
    turn = sim3.exp(np.array([0, 0, 0, np.radians(5.0), 0, 0, 0]))
    est = sim3.mul(turn[None], gt)
    est[:, :3] = gt[:, :3]
    rng = np.random.default_rng(0)
    truth = rng.uniform([-0.5, -1.0, 1.0], [1.5, 1.0, 2.0], (2000, 3))
    stamps = np.arange(n) / 30.0
    io.write_tum(tmp_path / "gt.txt", stamps, gt)
    io.write_tum(tmp_path / "est.txt", stamps, est)
    io.write_ply(tmp_path / "map.ply", sim3.act(turn, truth), np.zeros((len(truth), 3), np.uint8))
    io.write_ply(tmp_path / "truth.ply", truth, np.zeros((len(truth), 3), np.uint8))
    base = ["eval", tmp_path / "gt.txt", tmp_path / "est.txt", "--map", tmp_path / "map.ply",
            "--truth-cloud", tmp_path / "truth.ply"]  # fmt: skip
    code, out, err = _run(capsys, base)
    assert code == 0 and json.loads(out)["map_alignment"]["rotation_vs_orientations_deg"] > 4.9
    assert len(err.strip().splitlines()) == 1 and "note:" in err and "5.0°" in err
    code, out, err = _run(capsys, [*base, "--map-icp"])
    assert code == 0 and err == ""
