"""An offline structure-from-motion yardstick for a clip, and the depth placed by any trajectory.

Two questions about the dense-map figures of a short RGB-D clip (docs/evaluation.md §4.2):

1. **What does a strong offline pipeline score?** COLMAP's incremental SfM (``pycolmap``,
   optional: ``pip install pycolmap``) on the colour images at full resolution, SIFT
   features, sequential matching, one camera whose intrinsics it calibrates itself, once as
   a pinhole (``SIMPLE_PINHOLE``: f) and once with a radial term (``SIMPLE_RADIAL``: f, k1).
   Its trajectory is scored like a run's: ATE after Sim(3), rotation gain
   (:mod:`mslam.rotation_metrics`).
2. **What map could a trajectory give at best?** The folder's own depth images (every 10th
   matched frame, 1 cm voxels) placed by the trajectory's poses, then moved and scored
   exactly as ``mslam eval --map --truth-rgbd`` moves and scores a run's map: under the
   trajectory's Sim(3) and under the pose alignment (``--map-poses``). The depth is the
   truth's own, so whatever chamfer remains comes from the poses and the alignment alone.
   Any TUM trajectory can be added (``--trajectory NAME=FILE``, e.g. an mslam run's).

Usage: ``python benchmarks/sfm_baseline.py [--clip FOLDER] [--step 2] [--work DIR]
[--trajectory NAME=FILE ...]``; writes the section ``sfm-baseline`` of RESULTS.md unless
``--no-write``. SfM of 75 frames at 640x480 takes about 40 s per camera model on 2 cores
(80 s beside two mslam runs; RESULTS.md, section ``sfm-baseline``).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
from _results import git_rev, table, write_section

from mslam.datasets import load_sequence
from mslam.evaluate import associate, ate
from mslam.formats import read_tum
from mslam.map_metrics import evaluate_map, truth_from_rgbd, voxel_downsample
from mslam.rotation_metrics import rotation_report
from mslam_ref import so3
from mslam_ref.pointmap import camera_rays

CLIP = Path(__file__).resolve().parents[2] / "shared/data/seq/7scenes_redkitchen_f000000-000149"

#: Columns of the RESULTS table.
HEADER = ["trajectory", "frames", "intrinsics (640x480)", "ATE [cm]", "rotation gain",
          "depth at its poses: chamfer, trajectory Sim(3) [cm]", "pose alignment [cm]"]  # fmt: skip

#: Every how many matched frames the depth is placed (the truth takes every 5th).
DEPTH_STEP = 10
#: COLMAP camera models tried, in table order.
MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL")


def colmap_trajectory(images: list[Path], stamps: np.ndarray, work: Path, model: str, seed: int):
    """Incremental SfM of ``images`` with one self-calibrated camera of ``model``, RANSAC and
    mapping seeded with ``seed`` (runs with the same seed can still differ: threads).

    Returns ``(stamps, est, params)``: (n,) stamps and (n, 7) ``[t, q]`` camera-to-world poses
    of the registered images of the largest model, and the camera's parameters
    (``f, cx, cy[, k1]`` in pixels); None when nothing registers.
    """
    import pycolmap

    pycolmap.set_random_seed(seed)
    out = work / model
    shutil.rmtree(out, ignore_errors=True)
    (out / "images").mkdir(parents=True)
    for p in images:
        shutil.copy(p, out / "images" / p.name)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = 2
    extract.sift.max_num_features = 2048
    db = out / "database.db"
    pycolmap.extract_features(
        db, out / "images", camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
        extraction_options=extract, device=pycolmap.Device.cpu,
    )  # fmt: skip
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 12
    pycolmap.match_sequential(db, pairing_options=pairing)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.random_seed = seed
    models = pycolmap.incremental_mapping(db, out / "images", out / "sparse", options=mapping)
    if not models:
        return None
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    index = {p.name: k for k, p in enumerate(images)}
    rows = []
    for im in rec.images.values():
        M = np.eye(4)
        M[:3, :4] = im.cam_from_world().matrix()
        T_WC = np.linalg.inv(M)
        rows.append((index[im.name], T_WC))
    rows.sort(key=lambda r: r[0])
    est = np.array([np.concatenate([T[:3, 3], so3.from_matrix(T[:3, :3])]) for _, T in rows])
    params = next(iter(rec.cameras.values())).params
    return stamps[[k for k, _ in rows]], est, np.asarray(params, np.float64)


def depth_at_poses(seq, gt_index: np.ndarray, est: np.ndarray, scale: float) -> np.ndarray:
    """The folder's depth of every :data:`DEPTH_STEP`-th matched frame, in the estimate's frame.

    ``X = R_est · X_C / s + t_est`` with ``X_C`` the metric depth points and ``s`` the
    trajectory's Sim(3) scale (estimate → truth), so that the alignment brings them back to
    metres. Returns (N, 3), voxel-downsampled to 1 cm in metres.
    """
    parts = []
    for k in range(0, len(gt_index), DEPTH_STEP):
        f = seq[int(gt_index[k])]
        if f.depth is None:
            continue
        X_C = (f.depth[..., None] * camera_rays(seq.K, *f.shape))[f.depth > 0]
        R = so3.to_matrix(est[k, 3:7])
        parts.append(voxel_downsample(X_C @ R.T, 0.01) / scale + est[k, :3])
    return np.concatenate(parts)


def score(name: str, seq, truth, gt, gt_stamps, st, est, intrinsics: str) -> list[object]:
    """One table row for the trajectory ``(st, est)``."""
    res = ate(st, est, gt_stamps, gt)
    i_est, i_gt = associate(st, gt_stamps, 0.01)
    rot = rotation_report(st[i_est], est[i_est], gt[i_gt]) or {}
    points = depth_at_poses(seq, i_gt, est[i_est], res.scale)
    chamfer = []
    for refine in ("none", "poses"):
        m, _, _ = evaluate_map(points, st, est, gt_stamps, gt, truth, refine=refine)
        chamfer.append(f"{100 * m.chamfer:.2f}")
    gain = rot.get("rotation_gain")
    row = [name, len(i_est), intrinsics, f"{100 * res.rmse:.2f}",
           "–" if gain is None else f"{gain:.3f}", *chamfer]  # fmt: skip
    print(*row, flush=True)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--clip", type=Path, default=CLIP)
    ap.add_argument("--step", type=int, default=2, help="SfM on every STEP-th image")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--work", type=Path, default=Path("/tmp/mslam_sfm_baseline"))
    ap.add_argument("--trajectory", action="append", default=[], metavar="NAME=FILE")
    ap.add_argument("--no-sfm", action="store_true", help="only the --trajectory files")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    seq = load_sequence(args.clip)
    gt, gt_stamps = np.asarray(seq.T_WC)[:, :7], np.asarray(seq.timestamps)
    truth = truth_from_rgbd(seq)
    rows = [score("ground truth", seq, truth, gt, gt_stamps, gt_stamps, gt, "–")]
    if not args.no_sfm:
        try:
            import pycolmap  # noqa: F401
        except ImportError:
            print("pycolmap is not installed (pip install pycolmap); use --no-sfm", file=sys.stderr)
            return 2
        images = sorted(p for p in args.clip.iterdir() if ".color." in p.name)
        take = np.arange(0, len(images), args.step)
        for model in MODELS:
            for seed in args.seeds:
                name = f"COLMAP {model}, seed {seed}"
                got = colmap_trajectory(
                    [images[k] for k in take], gt_stamps[take], args.work, model, seed
                )
                if got is None:
                    rows.append([name, 0, "nothing registered", "–", "–", "–", "–"])
                    continue
                st, est, p = got
                k1 = f", k1 {p[3]:.3f}" if len(p) > 3 else ""
                rows.append(score(name, seq, truth, gt, gt_stamps, st, est, f"f {p[0]:.1f}{k1}"))
    for spec in args.trajectory:
        name, _, path = spec.partition("=")
        st, est = read_tum(path)
        rows.append(score(name, seq, truth, gt, gt_stamps, st, est, "(the run's)"))
    body = (
        f"`python benchmarks/sfm_baseline.py --step {args.step} --seeds "
        f"{' '.join(map(str, args.seeds))}` at {git_rev()}, "
        f"{args.clip.name}: COLMAP incremental SfM (pycolmap) on one colour image in {args.step} "
        "at 640x480, one self-calibrated camera; mslam runs added with `--trajectory`. "
        f"The last two columns: the clip's own depth of one matched frame in {DEPTH_STEP} "
        "placed by the trajectory's poses, scored as `mslam eval --map --truth-rgbd` scores a "
        f"map (truth {len(truth):,} points), under the trajectory's Sim(3) and under "
        "`--map-poses`.\n\n" + table(HEADER, rows)
    )
    if not args.no_write:
        write_section("sfm-baseline", "Offline SfM and the depth placed by each trajectory", body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
