"""mslam.rotation_metrics: the rotation gain and relative rotation error of a trajectory."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tolerances import F64_IDENTITY, F64_SOLVE

from mslam import formats as io
from mslam.cli import main
from mslam.rotation_metrics import associated_report, rotation_report, rotations
from mslam_ref import sim3, so3


def _walk(n: int = 90, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (n,) at 30 Hz and (n, 8) poses of a camera that walks and turns steadily
    (about 60° about a tilted axis in all, with a little wobble)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    phi = np.radians(60.0) * (t / t[-1])[:, None] * axis + rng.normal(0, 0.01, (n, 3))
    T = np.zeros((n, 8))
    T[:, :3] = np.stack([t, 0.2 * np.sin(t), 0.05 * t**2], -1)
    T[:, 3:7], T[:, 7] = so3.exp(phi), 1.0
    return t, T


def _turned(T: np.ndarray, gain: float) -> np.ndarray:
    """The poses with every orientation's rotation vector scaled by ``gain``."""
    out = T.copy()
    out[:, 3:7] = so3.exp(gain * so3.log(T[:, 3:7]))
    return out


def _report(stamps, est, gt):
    return associated_report(stamps, est, stamps, gt)


def test_a_perfect_estimate_in_another_frame_has_gain_one_and_no_error() -> None:
    t, gt = _walk()
    G = sim3.exp(np.array([0.5, -1.0, 2.0, 0.4, -0.2, 0.9, np.log(3.0)]))
    rep = _report(t, sim3.mul(G[None], gt), gt)
    assert rep is not None
    assert rep["rotation_gain"] == pytest.approx(1.0, abs=1e-9)
    assert rep["rotation_error_max_deg"] < 1e-5
    assert rep["rotation_lag_s"] == pytest.approx(0.5)


@pytest.mark.parametrize("gain", [0.8, 0.9, 1.15])
def test_an_estimate_that_turns_too_little_or_too_much_shows_its_gain(gain: float) -> None:
    t, gt = _walk()
    rep = _report(t, _turned(gt, gain), gt)
    assert rep is not None and rep["rotation_gain"] == pytest.approx(gain, abs=0.02)
    turn_per_lag_deg = 60.0 * 15 / 89  # 0.5 s of the 89-step walk
    assert rep["rotation_error_median_deg"] > 0.5 * abs(1 - gain) * turn_per_lag_deg


def test_a_constant_camera_offset_leaves_the_gain_at_one() -> None:
    t, gt = _walk()
    est = gt.copy()
    est[:, 3:7] = so3.mul(gt[:, 3:7], so3.exp(np.radians([3.0, -2.0, 1.0]))[None])
    rep = _report(t, est, gt)
    assert rep is not None and rep["rotation_gain"] == pytest.approx(1.0, abs=1e-6)


def test_noise_does_not_raise_the_gain() -> None:
    t, gt = _walk()
    rng = np.random.default_rng(1)
    est = gt.copy()
    est[:, 3:7] = so3.mul(so3.exp(rng.normal(0, np.radians(1.0), (len(t), 3))), gt[:, 3:7])
    rep = _report(t, est, gt)
    assert rep is not None and rep["rotation_gain"] == pytest.approx(1.0, abs=0.05)
    assert rep["rotation_error_median_deg"] > 1.0


def test_no_gain_for_a_camera_that_does_not_turn_and_none_for_positions() -> None:
    t, gt = _walk()
    gt[:, 3:7] = np.array([0.0, 0.0, 0.0, 1.0])
    rep = _report(t, gt, gt)
    assert rep is not None and rep["rotation_gain"] is None
    assert rotation_report(t, gt[:, :3], gt) is None
    assert rotations(gt[:, :3]) is None


def test_matrices_are_projected_onto_rotations() -> None:
    _, gt = _walk(10)
    M = sim3.to_matrix(gt)
    M[:, :3, :3] *= 1.0002  # stored matrices are often slightly off
    R = rotations(M)
    assert R is not None
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=F64_IDENTITY)
    assert np.allclose(R, so3.to_matrix(gt[:, 3:7]), atol=F64_SOLVE)


def test_mslam_eval_prints_the_rotation_figures(tmp_path, capsys) -> None:
    t, gt = _walk()
    io.write_tum(tmp_path / "gt.txt", t, gt)
    io.write_tum(tmp_path / "est.txt", t, _turned(gt, 0.85))
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["rotation_gain"] == pytest.approx(0.85, abs=0.02)
    assert res["rotation_error_median_deg"] > 0


def test_stamps_that_cannot_be_associated_give_no_report_not_an_error() -> None:
    t, gt = _walk()
    assert associated_report(t[:0], gt[:0], t, gt) is None
    assert associated_report(t + 100.0, gt, t, gt) is None
