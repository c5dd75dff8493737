"""What a plain depth-only tracker scores on a clip: a yardstick for the RGB-D figures.

Frame-to-keyframe point-to-plane ICP on the depth images alone (no colour, no graph, no
loop closure), a new keyframe every ``--keyframe-every`` frames; the map is the keyframes'
depth back-projected with the tracker's poses, voxel-downsampled to 1 cm. It is then scored
exactly as ``mslam eval --map ... --truth-rgbd`` scores a run: ATE, rotation gain, and the
dense-map metrics under the trajectory's Sim(3), under the pose alignment and after ICP
(docs/evaluation.md §4.2).

The point: on a short, nearly straight clip the map chamfer under the trajectory's Sim(3)
is set by how the positions pin the rotation about the path, not by how well the depth
images were put together. A tracker that only uses the depth, and whose map is those depth
images, shows what that alignment leaves for any depth-consistent map.

Usage: ``python benchmarks/depth_icp_baseline.py [--clip FOLDER] [--keyframe-every 10]``;
writes the section ``depth-icp-baseline`` of RESULTS.md unless ``--no-write``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _results import git_rev, table, write_section
from scipy.spatial import cKDTree

from mslam.datasets import load_sequence
from mslam.evaluate import ate
from mslam.map_metrics import evaluate_map, truth_from_rgbd, voxel_downsample
from mslam.rotation_metrics import rotation_report
from mslam_ref import so3
from mslam_ref.pointmap import camera_rays

#: Columns of the RESULTS table.
HEADER = ["map alignment", "accuracy [cm]", "completion [cm]", "chamfer [cm]",
          "trajectory vs orientations [°]"]  # fmt: skip

CLIP = Path(__file__).resolve().parents[2] / "shared/data/seq/7scenes_redkitchen_f000000-000149"

#: Pixel stride of the clouds ICP registers, and of the exported map (before the voxel grid).
ICP_STRIDE, MAP_STRIDE = 4, 2
#: ICP iterations per frame, largest pair distance (m), neighbours for a normal.
ICP_ITERS, ICP_MAX_DIST, NORMAL_K = 15, 0.05, 10


def cloud(depth: np.ndarray, K: np.ndarray, stride: int) -> np.ndarray:
    """(N, 3) camera-frame points of every ``stride``-th valid pixel of an (H, W) depth image."""
    X = depth[..., None] * camera_rays(K, *depth.shape)
    X = X[::stride, ::stride].reshape(-1, 3)
    return X[X[:, 2] > 0]


def normals(X: np.ndarray, tree: cKDTree) -> np.ndarray:
    """(N, 3) unit normals of (N, 3) points: the least-spread axis of each point's neighbours."""
    _, idx = tree.query(X, NORMAL_K)
    nb = X[idx] - X[idx].mean(axis=1, keepdims=True)
    _, V = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return V[:, :, 0]


def icp(A: np.ndarray, B: np.ndarray, T_AB: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_AB`` refined so that cloud ``B`` lands on cloud ``A`` (point-to-plane)."""
    tree = cKDTree(A)
    N_A = normals(A, tree)
    T = T_AB.copy()
    for _ in range(ICP_ITERS):
        Bt = B @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(Bt)
        ok = d < ICP_MAX_DIST
        p, q, n = Bt[ok], A[j[ok]], N_A[j[ok]]
        J = np.hstack([np.cross(p, n), n])
        x = np.linalg.lstsq(J, -np.sum((p - q) * n, axis=1), rcond=None)[0]
        dT = np.eye(4)
        dT[:3, :3] = so3.to_matrix(so3.exp(x[:3]))
        dT[:3, 3] = x[3:]
        T = dT @ T
    return T


def track(seq, every: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 4, 4) ``T_WC`` of every frame and the (P, 3) map of the keyframes' depth."""
    K = np.asarray(seq.K)
    T_WC, T_WK, T_KC = [np.eye(4)], np.eye(4), np.eye(4)
    key = cloud(seq[0].depth, K, ICP_STRIDE)
    parts, last_key = [voxel_downsample(cloud(seq[0].depth, K, MAP_STRIDE))], 0
    for i in range(1, len(seq)):
        depth = seq[i].depth
        T_KC = icp(key, cloud(depth, K, ICP_STRIDE), T_KC)
        T_WC.append(T_WK @ T_KC)
        if i - last_key >= every:
            T_WK, T_KC, last_key = T_WC[-1], np.eye(4), i
            key = cloud(depth, K, ICP_STRIDE)
            X = cloud(depth, K, MAP_STRIDE)
            parts.append(voxel_downsample(X @ T_WK[:3, :3].T + T_WK[:3, 3]))
    return np.stack(T_WC), voxel_downsample(np.concatenate(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--clip", type=Path, default=CLIP)
    ap.add_argument("--keyframe-every", type=int, default=10)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    seq = load_sequence(args.clip)
    T_WC, points = track(seq, args.keyframe_every)
    est = np.concatenate([T_WC[:, :3, 3], so3.from_matrix(T_WC[:, :3, :3])], axis=1)
    gt = np.asarray(seq.T_WC)[:, :7]
    stamps = np.asarray(seq.timestamps)
    truth = truth_from_rgbd(seq)
    res = ate(stamps, est, stamps, gt)
    rot = rotation_report(stamps, est, gt) or {}
    rows = []
    for refine in ("none", "poses", "icp"):
        m, _, info = evaluate_map(points, stamps, est, stamps, gt, truth, refine=refine)
        rows.append([refine, f"{100 * m.accuracy:.2f}", f"{100 * m.completion:.2f}",
                     f"{100 * m.chamfer:.2f}", f"{info['rotation_vs_orientations_deg']:.1f}"])  # fmt: skip
        print(*rows[-1], flush=True)
    body = (
        f"`python benchmarks/depth_icp_baseline.py --keyframe-every {args.keyframe_every}` at "
        f"{git_rev()}, {args.clip.name}: point-to-plane ICP of each frame's depth onto its "
        f"keyframe's, a keyframe every {args.keyframe_every} frames, no colour, no graph. "
        f"ATE {100 * res.rmse:.2f} cm (Sim(3) scale {res.scale:.3f}), rotation gain "
        f"{rot.get('rotation_gain') or float('nan'):.3f}; map {len(points):,} points (keyframe "
        f"depth at 1 cm), truth {len(truth):,}. Map metrics by the map alignment of "
        "`mslam eval` (`none`: the trajectory's Sim(3); `poses`: `--map-poses`; `icp`: "
        "`--map-icp`); the last column is the angle between the trajectory's Sim(3) rotation "
        "and the one that fits the cameras' orientations.\n\n" + table(HEADER, rows)
    )
    if not args.no_write:
        write_section("depth-icp-baseline", "A depth-only ICP tracker on the same clip", body)
    print(body)


if __name__ == "__main__":
    main()
