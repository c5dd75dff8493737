"""``colour_calibration``: colour images not registered to the depth images (7-Scenes) are
resampled onto the depth camera's pixel grid (``mslam.datasets.readers.Calibration.colour``)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from tolerances import REGISTRATION_ZOOM, REMAP_F32_PX

from mslam.cli import main
from mslam.datasets import load_sequence, read_calibration

W, H = 128, 96
ZOOM = 0.88  #: colour focal / depth focal (the Kinect v1 of 7-Scenes: about 520 / 585)


@pytest.fixture(scope="module")
def registered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reg") / "loop"
    assert main(["synth", "loop", "--out", str(out), "--frames", "3", "--width", str(W),
                 "--height", str(H), "--seed", "2"]) == 0  # fmt: skip
    return out


def _unregistered(registered: Path, dst: Path) -> tuple[Path, list[float]]:
    """A copy whose colour images come from a camera with ZOOM times the depth camera's focal
    length (a wider view, same centre), and the calibration naming both cameras."""
    shutil.copytree(registered, dst)
    cal = read_calibration(dst / "calib.yaml")
    colour = [ZOOM * cal.fx, ZOOM * cal.fy, cal.cx, cal.cy]
    # Colour pixel x sees the direction of depth pixel cx + (x - cx) / ZOOM.
    M = np.array([[1 / ZOOM, 0, cal.cx * (1 - 1 / ZOOM)], [0, 1 / ZOOM, cal.cy * (1 - 1 / ZOOM)]])
    for p in sorted((dst / "rgb").iterdir()):
        img = cv2.imread(str(p))
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP  # dst(x) = src(M x)
        size = img.shape[1::-1]
        wide = cv2.warpAffine(img, M, size, flags=flags, borderMode=cv2.BORDER_REPLICATE)
        cv2.imwrite(str(p), wide)
    text = (dst / "calib.yaml").read_text()
    (dst / "calib.yaml").write_text(text + f"colour_calibration: {colour}\n")
    return dst, colour


def _inner(a: np.ndarray) -> np.ndarray:
    return a[H // 8 : -H // 8, W // 8 : -W // 8].astype(float)


def test_colour_is_resampled_onto_the_depth_grid(registered: Path, tmp_path: Path) -> None:
    d, colour = _unregistered(registered, tmp_path / "unreg")
    cal = read_calibration(d / "calib.yaml")
    assert cal.colour == pytest.approx(tuple(colour))
    truth, seq = load_sequence(registered), load_sequence(d)
    np.testing.assert_array_equal(seq.K, truth.K)  # both cameras now share the depth's K
    raw = cv2.imread(str(sorted((d / "rgb").iterdir())[1]))[..., ::-1]
    for i in range(len(seq)):
        np.testing.assert_array_equal(seq[i].depth, truth[i].depth)
    err_after = np.abs(_inner(seq[1].rgb) - _inner(truth[1].rgb)).mean()
    err_before = np.abs(_inner(raw) - _inner(truth[1].rgb)).mean()
    assert err_after < 0.35 * err_before, (err_after, err_before)


def test_colour_calibration_errors(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    base = "width: 640\nheight: 480\ncalibration: [585, 585, 320, 240]\n"
    p.write_text(base + "colour_calibration: [520, 520, 320]\n")
    with pytest.raises(ValueError, match=r"c\.yaml: colour_calibration must be"):
        read_calibration(p)
    p.write_text(base + "colour_calibration: [0, 520, 320, 240]\n")
    with pytest.raises(ValueError, match="fx, fy > 0"):
        read_calibration(p)
    p.write_text(
        "width: 640\nheight: 480\ncalibration: [585, 585, 320, 240, 0.1, 0, 0, 0]\n"
        "colour_calibration: [520, 520, 320, 240]\n"
    )
    with pytest.raises(ValueError, match="cannot be combined with distortion"):
        read_calibration(p)
    p.write_text(base)
    assert read_calibration(p).colour is None


def test_colour_distortion_follows_opencv(tmp_path: Path) -> None:
    from mslam.datasets.readers import Calibration, colour_registration_maps

    colour = (520.0, 515.0, 318.0, 242.0, -0.12, 0.03, 0.001, -0.002, 0.01)
    cal = Calibration(64, 48, 585.0, 585.0, 32.0, 24.0, (), None, colour)
    mx, my = colour_registration_maps(cal)
    v, u = np.mgrid[0:48:7, 0:64:9].reshape(2, -1)
    rays = np.stack([(u - 32.0) / 585.0, (v - 24.0) / 585.0, np.ones(len(u))], -1)
    K_c = np.array([[520.0, 0, 318.0], [0, 515.0, 242.0], [0, 0, 1.0]])
    uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K_c, np.array(colour[4:]))
    np.testing.assert_allclose(
        np.stack([mx[v, u], my[v, u]], -1), uv.reshape(-1, 2), atol=REMAP_F32_PX
    )


def _frames(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    seq = load_sequence(folder)
    return [seq[i].rgb for i in range(len(seq))], [seq[i].depth for i in range(len(seq))]


@pytest.fixture(scope="module")
def registered_large(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reg") / "loop"
    assert main(["synth", "loop", "--out", str(out), "--frames", "4", "--width", "256",
                 "--height", "192", "--seed", "3"]) == 0  # fmt: skip
    return out


def test_edges_find_the_colour_zoom_and_leave_registered_images(
    registered_large: Path, tmp_path: Path
) -> None:
    """The edge search returns None on registered images and recovers the colour camera of
    unregistered ones; ``colour_calibration: auto`` then resamples them like the true value."""
    from mslam.datasets.registration import estimate_colour_intrinsics

    cal = read_calibration(registered_large / "calib.yaml")
    colour, info = estimate_colour_intrinsics(cal, *_frames(registered_large))
    assert colour is None and info["zoom"] == pytest.approx(1.0, abs=REGISTRATION_ZOOM)
    d, truth = _unregistered(registered_large, tmp_path / "unreg")
    text = (d / "calib.yaml").read_text().replace(f"colour_calibration: {truth}", "")
    (d / "calib.yaml").write_text(text + "colour_calibration: auto\n")
    seq = load_sequence(d)
    assert seq.calib.colour_auto and seq.calib.colour is None
    seq.register_colour()
    assert seq.colour_registration["applied"]
    assert seq.colour_registration["zoom"] == pytest.approx(ZOOM, abs=REGISTRATION_ZOOM)
    assert seq.calib.colour[0] == pytest.approx(truth[0], rel=REGISTRATION_ZOOM)
    (d / "calib.yaml").write_text(text + "colour_calibration: none\n")
    off = load_sequence(d)
    off.register_colour()
    assert off.colour_registration is None and off.calib.colour is None


def test_seven_scenes_folders_estimate_unless_told(tmp_path: Path) -> None:
    """7-Scenes stores unregistered colour and depth: its folders ask for the estimate unless the
    calibration names the colour camera or says ``none``."""
    from mslam.datasets.folders import load_7scenes

    img = np.zeros((48, 64, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "frame-000000.color.png"), img)
    cv2.imwrite(str(tmp_path / "frame-000000.depth.png"), np.full((48, 64), 1000, np.uint16))
    base = "width: 64\nheight: 48\ncalibration: [60, 60, 32, 24]\ndepth_scale: 1000\n"
    for extra, auto in (("", True), ("colour_calibration: none\n", False),
                        ("colour_calibration: [50, 50, 32, 24]\n", False)):  # fmt: skip
        (tmp_path / "calib.yaml").write_text(base + extra)
        assert load_7scenes(tmp_path).calib.colour_auto is auto
