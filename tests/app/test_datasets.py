"""Loaders: round trips for every layout, calibration files, and clear errors on bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from tolerances import (
    F64_CONDITIONED,
    F64_IDENTITY,
    F64_SOLVE,
    F64_ULPS,
    SEVEN_SCENES_POSE,
    TEXT_6_DECIMALS,
    TUM_DEPTH_STEP,
)

from mslam.cli import main
from mslam.datasets import (
    Calibration,
    Frame,
    load_sequence,
    read_calibration,
    subsample_sequence,
    write_tum_sequence,
)
from mslam.datasets.readers import encode_png
from mslam.datasets.synthetic import make_sequence
from mslam.formats import read_tum
from mslam_ref import sim3

W, H = 64, 48


@pytest.fixture(scope="module")
def tum_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tum") / "loop"
    rc = main(["synth", "loop", "--out", str(out), "--frames", "8", "--width", str(W),
               "--height", str(H), "--seed", "4"])  # fmt: skip
    assert rc == 0
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_synth_tum_round_trip(tum_dir: Path) -> None:
    ref = make_sequence("loop", n_frames=8, width=W, height=H, seed=4)
    seq = load_sequence(tum_dir)
    assert len(seq) == 8 and seq.has_depth and seq.T_WC is not None
    np.testing.assert_allclose(seq.K, ref.K, rtol=F64_IDENTITY)
    np.testing.assert_allclose(seq.timestamps, ref.timestamps, atol=TEXT_6_DECIMALS)
    for i in (0, 7):
        a, b = seq[i], ref[i]
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_allclose(a.depth, b.depth, atol=TUM_DEPTH_STEP)
        np.testing.assert_allclose(
            sim3.to_matrix(a.T_WC), sim3.to_matrix(b.T_WC), atol=F64_CONDITIONED
        )
    cal = read_calibration(tum_dir / "calib.yaml")
    assert (cal.width, cal.height, cal.depth_scale) == (W, H, 5000.0)
    t, T = read_tum(tum_dir / "groundtruth.txt")
    assert t.shape == (8,) and T.shape == (8, 7)
    raw = cv2.imread(str(next((tum_dir / "depth").iterdir())), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (H, W)


def test_tum_without_associations(tum_dir: Path, tmp_path: Path) -> None:
    d = _copy(tum_dir, tmp_path / "noassoc")
    (d / "associations.txt").unlink()
    seq = load_sequence(d)
    assert len(seq) == 8 and seq.has_depth
    (d / "depth.txt").unlink()
    assert not load_sequence(d).has_depth


def test_tum_builtin_freiburg_calibration(tum_dir: Path, tmp_path: Path) -> None:
    d = _copy(tum_dir, tmp_path / "rgbd_dataset_freiburg3_office")
    (d / "calib.yaml").unlink()
    seq = load_sequence(d)
    np.testing.assert_allclose(seq.K[0], [535.4, 0, 320.1])
    with pytest.raises(ValueError, match="does not match the calibration"):
        seq[0]  # the synthetic images are 64x48, not 640x480


def test_calibration_with_distortion_undistorts(tum_dir: Path, tmp_path: Path) -> None:
    calib = tmp_path / "cam.yaml"
    calib.write_text(f"width: {W}\nheight: {H}\ncalibration: [50, 50, 30, 25, 0.1, -0.05, 0, 0]\n")
    seq = load_sequence(tum_dir, calib=calib)
    np.testing.assert_allclose(seq.K[:2, 2], [(W - 1) / 2, (H - 1) / 2], atol=F64_SOLVE)
    assert abs(seq.K[0, 0] / seq.K[1, 1] - 1.0) < 1e-12
    f = seq[1]
    assert f.rgb.shape == (H, W, 3) and f.depth.shape == (H, W)


def _without_depth_scale(d: Path) -> Path:
    lines = (d / "calib.yaml").read_text().splitlines()
    (d / "calib.yaml").write_text("\n".join(ln for ln in lines if "depth_scale" not in ln) + "\n")
    return d


def test_depth_scale_assumed_only_where_nothing_states_it(tum_dir: Path, tmp_path: Path) -> None:
    """A TUM-layout folder's 5000 units per metre is an assumption unless its calibration, TUM's
    own folder names or ETH3D's ``calibration.txt`` state it; with ``depth_scale`` given, the
    depth follows it."""
    assert not load_sequence(tum_dir).depth_scale_assumed  # calib.yaml states 5000
    d = _without_depth_scale(_copy(tum_dir, tmp_path / "realsense"))
    seq = load_sequence(d)
    assert seq.depth_scale_assumed and seq.depth_scale == 5000.0
    mm = tmp_path / "mm.yaml"
    mm.write_text((d / "calib.yaml").read_text() + "depth_scale: 1000\n")
    in_mm = load_sequence(d, calib=mm)
    assert not in_mm.depth_scale_assumed and in_mm.depth_scale == 1000.0
    z5, z1 = seq[2].depth, in_mm[2].depth
    valid = z5 > 0
    assert valid.any()
    np.testing.assert_allclose(z1[valid], 5 * z5[valid], rtol=F64_ULPS)
    tum = _without_depth_scale(_copy(tum_dir, tmp_path / "rgbd_dataset_freiburg1_x"))
    (tum / "calib.yaml").unlink()
    assert not load_sequence(tum).depth_scale_assumed
    (d / "associations.txt").unlink()
    (d / "depth.txt").unlink()
    assert not load_sequence(d).depth_scale_assumed  # no depth, nothing assumed


def test_subsample_and_resize(tum_dir: Path) -> None:
    seq = load_sequence(tum_dir, subsample=3, size=(32, 24))
    assert len(seq) == 3 and seq.T_WC.shape == (3, 8)
    f = seq[1]
    assert f.index == 1 and f.rgb.shape == (24, 32, 3) and f.depth.shape == (24, 32)
    assert f.timestamp == pytest.approx(3 / 30, abs=1e-6)
    np.testing.assert_allclose(seq.K[0, 0], make_sequence("loop", 8, W, H, 4).K[0, 0] / 2)
    syn = load_sequence("synthetic:rotation", subsample=2, n_frames=6, width=W, height=H)
    assert len(syn) == 3 and syn[2].index == 2
    np.testing.assert_array_equal(syn[2].T_WC, make_sequence("rotation", 6, W, H).T_WC[4])
    assert len(subsample_sequence(syn, 2)) == 2


def test_image_folder(tmp_path: Path) -> None:
    ref = make_sequence("forward", n_frames=3, width=W, height=H, seed=1)
    names = ["img10.png", "img2.jpg", "img1.png"]
    for name, i in zip(names, (2, 1, 0)):
        _, buf = cv2.imencode(Path(name).suffix, cv2.cvtColor(ref[i].rgb, cv2.COLOR_RGB2BGR))
        (tmp_path / name).write_bytes(buf.tobytes())
    (tmp_path / "notes.txt").write_text("ignored")
    seq = load_sequence(tmp_path)
    assert len(seq) == 3 and seq.K is None and not seq.has_depth and seq.T_WC is None
    np.testing.assert_array_equal(seq[0].rgb, ref[0].rgb)  # natsorted: img1, img2, img10
    np.testing.assert_array_equal(seq[2].rgb, ref[2].rgb)
    assert seq[2].timestamp == pytest.approx(2 / 30)


def _write_mjpg(path: Path, ref) -> Path:
    """``ref``'s frames as an MJPG video at 15 frames/s (skips where OpenCV cannot write it)."""
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (W, H))
    if not wr.isOpened():
        pytest.skip("OpenCV build cannot write MJPG video")
    for f in ref:
        wr.write(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
    wr.release()
    return path


def test_video(tmp_path: Path) -> None:
    ref = make_sequence("loop", n_frames=10, width=W, height=H, seed=2)
    path = _write_mjpg(tmp_path / "clip.avi", ref)
    seq = load_sequence(path)
    assert len(seq) == 10 and seq.K is None
    assert seq[3].timestamp == pytest.approx(3 / 15.0)
    assert np.abs(seq[3].rgb.astype(int) - ref[3].rgb).mean() < 12
    sub = load_sequence(path, subsample=3)
    assert len(sub) == 4
    assert np.abs(sub[2].rgb.astype(int) - ref[6].rgb).mean() < 12
    assert np.abs(sub[1].rgb.astype(int) - ref[3].rgb).mean() < 12  # backwards seek


class _CountingCapture:
    """A ``cv2.VideoCapture`` that counts its seeks."""

    def __init__(self, cap) -> None:
        self.cap, self.seeks = cap, 0

    def set(self, *args):
        self.seeks += 1
        return self.cap.set(*args)

    def __getattr__(self, name):
        return getattr(self.cap, name)


def test_video_skips_forward_by_decoding_and_reads_the_frames_a_seek_reads(
    tmp_path: Path,
) -> None:
    from mslam.datasets.folders import GRAB_AHEAD

    ref = make_sequence("loop", n_frames=40, width=W, height=H, seed=2)
    path = _write_mjpg(tmp_path / "clip.avi", ref)
    seq = load_sequence(path)
    seq[0]
    seq._cap = counting = _CountingCapture(seq._cap)
    # after frame 9 the next is 10: a skip of exactly GRAB_AHEAD decodes; back to 2 and from 3
    # on to 39 (a skip longer than GRAB_AHEAD) seek
    order = [3, 4, 9, 10 + GRAB_AHEAD, 2, 39]
    frames = [seq[i].rgb for i in order]
    assert counting.seeks == 2
    for i, rgb in zip(order, frames, strict=True):
        alone = load_sequence(path)
        alone._load(0)
        alone._cap.set(cv2.CAP_PROP_POS_FRAMES, i)  # what a seek reads
        ok, bgr = alone._cap.read()
        assert ok
        np.testing.assert_array_equal(rgb, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


def test_euroc(tmp_path: Path) -> None:
    ref = make_sequence("forward", n_frames=4, width=W, height=H, seed=3)
    cam = tmp_path / "MH_01" / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    t0 = 1403636579763555584
    rows = ["#timestamp [ns],filename"]
    for i, f in enumerate(ref):
        name = f"{t0 + i * 50_000_000}.png"
        cv2.imwrite(str(cam / "data" / name), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY))
        rows.append(f"{t0 + i * 50_000_000},{name}")
    (cam / "data.csv").write_text("\n".join(rows) + "\n")
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [1, 0, 0, 0.1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n"
        f"resolution: [{W}, {H}]\nintrinsics: [40.0, 41.0, 31.0, 24.0]\n"
        "distortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]\n"
    )
    gt = tmp_path / "MH_01" / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    lines = ["#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z"]
    for i in range(4):
        lines.append(f"{t0 + i * 50_000_000},{i * 0.1},0,1,1,0,0,0")
    (gt / "data.csv").write_text("\n".join(lines) + "\n")
    seq = load_sequence(tmp_path / "MH_01")
    assert len(seq) == 4 and not seq.has_depth
    np.testing.assert_allclose(seq.K[:2, 2], [(W - 1) / 2, (H - 1) / 2], atol=F64_SOLVE)
    f = seq[2]
    assert f.rgb.shape == (H, W, 3) and np.all(f.rgb[..., 0] == f.rgb[..., 1])
    assert f.timestamp == pytest.approx((t0 + 2 * 50_000_000) * 1e-9)
    np.testing.assert_allclose(seq.T_WC[2, :3], [0.3, 0, 1], atol=F64_IDENTITY)


def test_seven_scenes(shared_data: Path) -> None:
    folder = shared_data / "seq" / "7scenes_redkitchen_f000000-000149"
    seq = load_sequence(folder)
    assert len(seq) == 150 and seq.has_depth
    np.testing.assert_allclose(seq.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    f = seq[20]
    assert f.rgb.shape == (480, 640, 3)
    valid = f.depth > 0
    assert 0.5 < valid.mean() and 0.3 < np.median(f.depth[valid]) < 5.0
    M = np.loadtxt(folder / "frame-000020.pose.txt")
    np.testing.assert_allclose(sim3.to_matrix(f.T_WC), M, atol=SEVEN_SCENES_POSE)
    _, T = read_tum(folder / "groundtruth.txt")
    np.testing.assert_allclose(seq.T_WC[:, :3], T[:, :3], atol=TEXT_6_DECIMALS)
    sub = load_sequence(folder, subsample=10, size=(160, 120))
    assert len(sub) == 15 and sub[1].rgb.shape == (120, 160, 3) and sub[1].index == 1
    np.testing.assert_allclose(sub.K[0, 0], 585 / 4)


# -- bad input ------------------------------------------------------------------------------


def test_missing_and_unknown_sources(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_sequence(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="unknown layout"):
        load_sequence(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match=r"notes\.txt"):
        load_sequence(tmp_path / "notes.txt")
    with pytest.raises(ValueError, match="subsample"):
        load_sequence("synthetic:loop", subsample=0)


def test_bad_files_name_the_file(tum_dir: Path, tmp_path: Path) -> None:
    d = _copy(tum_dir, tmp_path / "bad")
    rgb = sorted((d / "rgb").iterdir())
    depth = sorted((d / "depth").iterdir())
    rgb[1].write_bytes(rgb[1].read_bytes()[:100])  # truncated PNG
    rgb[2].unlink()
    depth[3].write_bytes(encode_png(np.zeros((H - 1, W), np.uint16)))  # wrong size
    depth[4].write_bytes(encode_png(np.zeros((H, W, 3), np.uint8)))  # not 16-bit
    seq = load_sequence(d)
    seq[0]
    with pytest.raises(ValueError, match=rgb[1].name):
        seq[1]
    with pytest.raises(FileNotFoundError, match=rgb[2].name):
        seq[2]
    with pytest.raises(ValueError, match=f"{depth[3].name}.*does not match"):
        seq[3]
    with pytest.raises(ValueError, match=f"{depth[4].name}.*16-bit"):
        seq[4]
    (d / "associations.txt").write_text("0.0 rgb/x.png\n")
    with pytest.raises(ValueError, match=r"associations.txt:1"):
        load_sequence(d)


def test_truncated_jpeg(tmp_path: Path) -> None:
    img = make_sequence("loop", 2, W, H)[0].rgb
    _, buf = cv2.imencode(".jpg", img)
    (tmp_path / "a.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    with pytest.raises(ValueError, match=r"a\.jpg"):
        load_sequence(tmp_path)[0]


def test_calibration_errors(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("width: 640\ncalibration: [500, 500, 320, 240]\n")
    with pytest.raises(ValueError, match=r"c\.yaml.*height"):
        read_calibration(p)
    p.write_text("width: 640\nheight: 480\ncalibration: [500, 500, 320]\n")
    with pytest.raises(ValueError, match=r"c\.yaml.*calibration"):
        read_calibration(p)
    p.write_text("width: [640\n")
    with pytest.raises(ValueError, match=r"c\.yaml.*YAML"):
        read_calibration(p)
    with pytest.raises(FileNotFoundError, match=r"none\.yaml"):
        read_calibration(tmp_path / "none.yaml")
    p.write_text("width: 640\nheight: 480\ncalibration: [500, 501, 320, 240, 0.1, 0, 0, 0, 0.01]\n")
    cal = read_calibration(p)
    assert cal == Calibration(640, 480, 500, 501, 320, 240, (0.1, 0, 0, 0, 0.01), None)


def test_synth_command_errors_leave_nothing(tmp_path: Path, monkeypatch, capsys) -> None:
    assert main(["synth", "spiral", "--out", str(tmp_path / "a")]) == 2
    assert "unknown synthetic path" in capsys.readouterr().err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep")
    assert main(["synth", "loop", "--out", str(tmp_path / "full"), "--frames", "3"]) == 2
    assert (tmp_path / "full" / "x").read_text() == "keep"

    import mslam.datasets.tum as tum

    calls = {"n": 0}

    def failing(img):
        calls["n"] += 1
        if calls["n"] > 3:
            raise ValueError("disk full")
        return encode_png(img)

    monkeypatch.setattr(tum, "encode_png", failing)
    out = tmp_path / "partial"
    assert main(["synth", "loop", "--out", str(out), "--frames", "5", "--width", "16",
                 "--height", "12"]) == 2  # fmt: skip
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full"]


def test_frame_validation() -> None:
    with pytest.raises(ValueError, match="rgb"):
        Frame(0, 0.0, np.zeros((4, 4, 3)))
    with pytest.raises(ValueError, match="depth"):
        Frame(0, 0.0, np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="T_WC"):
        Frame(0, 0.0, np.zeros((4, 4, 3), np.uint8), None, np.zeros(7))


def test_write_tum_refuses_non_empty(tmp_path: Path) -> None:
    seq = make_sequence("loop", 2, 16, 12)
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "f").write_text("")
    with pytest.raises(ValueError, match="not empty"):
        write_tum_sequence(seq, tmp_path / "x")
    write_tum_sequence(seq, tmp_path / "x", overwrite=True)
    assert len(load_sequence(tmp_path / "x")) == 2
