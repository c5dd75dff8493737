"""``mslam run --rerun/--colmap/--depth``: the recording reads back, COLMAP reads the model, the
depth maps agree with the PLY, and every export is part of the one atomic output set."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from tolerances import (
    COLMAP_POSE_ATOL,
    DEPTH_VS_PLY_MEDIAN_REL,
    F64_IDENTITY,
    FOCAL_FROM_POINTMAP_RTOL,
    RERUN_F32_POSITION,
)

from mslam.cli import main
from mslam.export.camera import focal_from_pointmap
from mslam.export.depth import render_depth
from mslam.formats import read_ply, read_tum
from mslam_ref import so3
from mslam_ref.pointmap import backproject, intrinsics_from_fov

rerun_chunk = pytest.importorskip("rerun.chunk")

LOOP = "synthetic:loop:24:64x48"
JUMP = "synthetic:jump:30:64x48"  # lost at frame 15, relocalised at frame 16


def _run(out: Path, source: str, *extra: str) -> int:
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    args = ["run", source, "--out", str(out), "--kernels", "fast", "--quiet"]
    return main([*args, "--rerun", str(out / "run.rrd"), *extra])


@pytest.fixture(scope="module")
def loop_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("exports") / "O"
    assert _run(out, LOOP, "--colmap", str(out / "colmap"), "--depth") == 0
    return out


@pytest.fixture(scope="module")
def jump_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("exports_jump") / "O"
    assert _run(out, JUMP, "--colmap", str(out / "colmap"), "--colmap-images", "frames") == 0
    return out


def _chunks(path: Path) -> dict[str, list]:
    """Entity path -> its chunks' record batches (pyarrow), read back with rerun-sdk."""
    out: dict[str, list] = {}
    for chunk in rerun_chunk.RrdReader(str(path)).store().stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches: list, name: str) -> list:
    rows = []
    for b in batches:
        if name in b.schema.names:
            rows += b.column(name).to_pylist()
    return rows


def _texts(batches: list) -> list[str]:
    return [t for row in _column(batches, "TextLog:text") for t in row]


def test_recording_holds_the_run(loop_dir: Path):
    s = json.loads((loop_dir / "summary.json").read_text())
    ent = _chunks(loop_dir / "run.rrd")
    # one status and one image per frame on the `frame` timeline; a pose for every posed frame
    assert sorted(_column(ent["/status"], "frame")) == list(range(s["frames"]))
    assert len(_column(ent["/world/camera/image"], "Image:buffer")) == s["frames"]
    assert len(_column(ent["/world/camera"], "Transform3D:translation")) == s["frames_with_pose"]
    assert len(_column(ent["/world/camera/image"], "Pinhole:image_from_camera")) == 1
    # every keyframe: a Sim(3) pose, and its pointmap with colours and one confidence per point
    kts, kT = read_tum(loop_dir / "keyframes.txt")
    for k in range(len(kts)):
        pts = ent[f"/world/keyframes/{k}/points"]
        pos, col = _column(pts, "Points3D:positions"), _column(pts, "Points3D:colors")
        conf = _column(pts, "confidence")
        assert len(pos[-1]) == len(col[-1]) == len(conf[-1]) > 1000
        t = _column(ent[f"/world/keyframes/{k}"], "Transform3D:translation")[-1]
        np.testing.assert_allclose(
            np.ravel(t), kT[k, :3], atol=RERUN_F32_POSITION
        )  # the final pose last
    # refined by fusion: keyframe 0's pointmap logged again, with moved points
    kf0 = _column(ent["/world/keyframes/0/points"], "Points3D:positions")
    assert len(kf0) >= 2 and np.abs(np.array(kf0[-1]) - np.array(kf0[0])).max() > 1e-4
    # graph edges with their match fractions; the last state is the final graph
    consecutive = _column(ent["/world/graph/consecutive"], "match_frac")[-1]
    loops = _column(ent["/world/graph/loop_closure"], "match_frac")[-1]
    assert len(consecutive) + len(loops) == s["edges"] and len(loops) == s["loop_closure_edges"] > 0
    assert all(0.0 <= f <= 1.0 for f in consecutive + loops)
    # ground truth, aligned into the run's world: close to the final estimate
    gt = np.array(_column(ent["/world/ground_truth"], "LineStrips3D:strips")[0][0])
    est = np.array(_column(ent["/world/trajectory"], "LineStrips3D:strips")[0][0])
    assert gt.shape == est.shape == (s["frames"], 3)
    assert np.sqrt(np.mean(np.sum((gt - est) ** 2, axis=1))) < 2 * s["ate_rmse"] / s["ate"]["scale"]


def test_recording_shows_relocalisation_and_lost_frames(jump_dir: Path):
    s = json.loads((jump_dir / "summary.json").read_text())
    ent = _chunks(jump_dir / "run.rrd")
    assert s["relocalisations"] == 1
    events = _texts(ent["/events/reloc"])
    assert len(events) == 1
    assert events[0].startswith(f"frame {s['relocalised_at'][0]} relocalised as keyframe ")
    assert len(_column(ent["/world/reloc"], "Points3D:positions")) == 1
    lost = [t for t in _texts(ent["/status"]) if t.endswith(": lost")]
    assert len(lost) == s["lost_frames"] > 0
    assert len(_column(ent["/world/camera"], "Transform3D:translation")) == s["frames_with_pose"]


def test_colmap_model_reads_back_with_the_keyframe_poses(loop_dir: Path):
    pycolmap = pytest.importorskip("pycolmap")
    kts, kT = read_tum(loop_dir / "keyframes.txt")
    xyz, _ = read_ply(loop_dir / "reconstruction.ply")
    for files in ("txt", "bin"):
        model_dir = loop_dir / "colmap" if files == "txt" else _only(loop_dir / "colmap", "bin")
        rec = pycolmap.Reconstruction(str(model_dir))
        assert len(rec.images) == len(kts)
        assert rec.num_points3D() == len(xyz)  # the PLY's points
        for n, (iid, im) in enumerate(sorted(rec.images.items())):
            assert iid == n + 1 and (loop_dir / "colmap" / "images" / im.name).is_file()
            np.testing.assert_allclose(im.projection_center(), kT[n, :3], atol=COLMAP_POSE_ATOL)
            R_cw = im.cam_from_world().rotation.matrix()
            R_wc = so3.to_matrix(kT[n, 3:7])
            np.testing.assert_allclose(R_cw.T, R_wc, atol=COLMAP_POSE_ATOL)
        assert rec.compute_mean_reprojection_error() < 1.0  # pixels, estimated focal length
    cam = pycolmap.Reconstruction(str(loop_dir / "colmap")).cameras[1]
    W, H, fx, fy, cx, cy = np.loadtxt(loop_dir / "depth" / "intrinsics.txt")
    assert (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose(cam.params, [fx, fy, cx + 0.5, cy + 0.5])


def _only(folder: Path, ext: str) -> Path:
    """A sibling folder holding only the ``ext`` model files (pycolmap prefers .bin anyway)."""
    import shutil

    sub = folder.parent / f"colmap_{ext}"
    sub.mkdir(exist_ok=True)
    for name in ("cameras", "images", "points3D"):
        shutil.copy(folder / f"{name}.{ext}", sub)
    return sub


def test_colmap_every_frame_option(jump_dir: Path):
    pycolmap = pytest.importorskip("pycolmap")
    ts, T = read_tum(jump_dir / "trajectory.txt")
    rec = pycolmap.Reconstruction(str(jump_dir / "colmap"))
    assert len(rec.images) == len(ts)
    centres = np.array([im.projection_center() for _, im in sorted(rec.images.items())])
    np.testing.assert_allclose(centres, T[:, :3], atol=COLMAP_POSE_ATOL)


def test_depth_maps_match_the_point_cloud(loop_dir: Path):
    ts, T = read_tum(loop_dir / "trajectory.txt")
    rows = np.loadtxt(loop_dir / "depth" / "frames.txt", ndmin=2)
    assert len(rows) == len(ts)
    np.testing.assert_allclose(rows[:, 1], ts)
    W, H, fx, fy, cx, cy = np.loadtxt(loop_dir / "depth" / "intrinsics.txt")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    xyz, _ = read_ply(loop_dir / "reconstruction.ply")
    for row, pose in zip(rows, T):
        stem = loop_dir / "depth" / f"{int(row[0]):06d}"
        mm = cv2.imread(f"{stem}.png", cv2.IMREAD_UNCHANGED)
        depth, conf = np.load(f"{stem}.npy"), np.load(f"{stem}_conf.npy")
        assert mm.dtype == np.uint16 and mm.shape == depth.shape == conf.shape == (H, W)
        assert np.all((mm > 0) == (conf > 1.5) & (depth > 0))  # the mask is the confidence's
        ply, _ = render_depth(xyz, np.ones(len(xyz)), np.append(pose, 1.0), K, (int(H), int(W)))
        both = (mm > 0) & (ply > 0)
        assert both.mean() > 0.3
        rel = np.abs(mm[both] / 1000.0 - ply[both]) / ply[both]
        assert np.median(rel) < DEPTH_VS_PLY_MEDIAN_REL


def test_focal_length_from_exact_pointmaps():
    K = intrinsics_from_fov(64, 48, 70.0)
    rng = np.random.default_rng(0)
    X = backproject(rng.uniform(1.0, 4.0, (48, 64)), K)
    K_est = focal_from_pointmap(X, np.full((48, 64), 2.0))
    np.testing.assert_allclose(K_est, K, rtol=FOCAL_FROM_POINTMAP_RTOL)


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--rerun", "elsewhere.rrd"], "must name a path inside --out"),
        (["--rerun", "{out}/run.txt"], "ending in .rrd"),
        (["--colmap", "{out}/summary.json"], "one of the run's own outputs"),
    ],
)
def test_bad_export_options_exit_2_before_work(tmp_path, capsys, flags, message):
    out = tmp_path / "O"
    flags = [f.format(out=out) for f in flags]
    rc = main(["run", LOOP, "--out", str(out), "--quiet", *flags])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and err.count("\n") == 1
    assert not out.exists()


def test_a_failing_export_leaves_nothing(tmp_path, monkeypatch, capsys):
    import mslam.export.colmap as colmap

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(colmap, "write_colmap", broken)
    out = tmp_path / "O"
    rc = _run(out, "synthetic:loop:6:64x48", "--colmap", str(out / "colmap"))
    assert rc == 2 and "No space left on device" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.iterdir())  # no set, no temporary recording


def test_spawn_without_a_display_records_the_file_and_warns(tmp_path, monkeypatch):
    from mslam.export.rerun_log import RerunRecorder

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    monkeypatch.setattr("mslam.export.rerun_log._viewer_listening", lambda port=None: False)
    with pytest.warns(RuntimeWarning, match="no display"):
        rec = RerunRecorder(tmp_path / "r.rrd", spawn=True)
    rec.on_frame(0, np.zeros((4, 6, 3), np.uint8), None, "lost")
    rec.close()
    assert _texts(_chunks(tmp_path / "r.rrd")["/status"]) == ["frame 0: lost"]


def test_given_intrinsics_are_written_verbatim(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    K = intrinsics_from_fov(64, 48, 70.0)
    calib = tmp_path / "calib.yaml"
    fx, cx, cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
    calib.write_text(f"width: 64\nheight: 48\ncalibration: [{fx!r}, {fx!r}, {cx!r}, {cy!r}]\n")
    out = tmp_path / "O"
    rc = _run(out, "synthetic:loop:6:64x48", "--calib", str(calib), "--colmap", str(out / "c"))
    assert rc == 0
    cam = pycolmap.Reconstruction(str(out / "c")).cameras[1]
    np.testing.assert_allclose(cam.params, [fx, fx, cx + 0.5, cy + 0.5], rtol=F64_IDENTITY)
    assert "# Intrinsics: given" in (out / "c" / "cameras.txt").read_text()
