"""Paper §4.2 (Table 3) — dense-map metrics: accuracy, completion and chamfer of a run's map.

Method (docs/evaluation.md, section 4.1):

1. **Truth.** Either a given point cloud, or :func:`truth_from_rgbd`: the depth of every 5th
   frame of an RGB-D folder (7-Scenes or TUM layout) back-projected with the folder's
   intrinsics at the native resolution, moved into the world by the frame's ground-truth pose,
   and voxel-downsampled to 1 cm (one centroid per occupied voxel, :func:`voxel_downsample`).
   Only frames inside the estimate's time span count, so a run over part of a sequence is
   compared with the part it saw.
2. **Alignment.** The map (``reconstruction.ply``) is moved by the transform that aligns the
   run's ``trajectory.txt`` to the ground-truth trajectory: ``mslam.evaluate.ate`` with evo's
   association and Umeyama's Sim(3) (``x -> s R x + t``, :func:`align_points`). Optionally
   (``refine="icp"``, the paper's 7-Scenes protocol) :func:`icp_refine` then registers the map
   rigidly onto the truth, starting from that transform and keeping its scale. Umeyama fits
   positions only: on a short, nearly straight path the rotation about the path is weakly
   determined, so the result also reports :func:`orientation_disagreement`, the angle between
   the fitted rotation and the one the camera orientations imply (a few degrees move points
   metres away by centimetres).
3. **Distances.** Nearest neighbours with ``scipy.spatial.cKDTree`` both ways, each over at most
   200 000 points drawn at random with a fixed seed (results are reproducible):

   * accuracy = mean distance map -> truth; completion = mean distance truth -> map;
   * chamfer = (accuracy + completion) / 2;
   * far = fraction of map points farther than 0.5 m from every true point;
   * the medians of both distance sets, and the paper's form (RMSE of the distances capped at
     0.5 m, as ``mslam.evaluate.reconstruction_metrics``).

Means are not capped: a map point 2 m off costs 2 m in ``accuracy`` and also shows in ``far``.

Public names, in reading order:
    MAX_POINTS, FAR_DIST, VOXEL, FRAME_STEP, MapMetrics, voxel_downsample, truth_from_rgbd,
    align_points, orientation_disagreement, icp_refine, map_metrics, evaluate_map
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mslam.rotation_metrics import angle_deg
from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray, as_float_array
from mslam_ref.pointmap import camera_rays

__all__ = [
    "FAR_DIST",
    "FRAME_STEP",
    "MAX_POINTS",
    "VOXEL",
    "MapMetrics",
    "align_points",
    "evaluate_map",
    "icp_refine",
    "map_metrics",
    "orientation_disagreement",
    "truth_from_rgbd",
    "voxel_downsample",
]

#: Largest number of points whose nearest distances are averaged, each way.
MAX_POINTS = 200_000
#: A map point farther than this (m) from every true point counts as "far" (paper's cap).
FAR_DIST = 0.5
#: Voxel edge (m) of the downsampled truth.
VOXEL = 0.01
#: Every FRAME_STEP-th RGB-D frame is back-projected into the truth.
FRAME_STEP = 5
#: ICP: iterations, correspondence distance (m) of the first and last one (geometric schedule
#: in between), and the number of map points taking part.
ICP_ITERS = 30
ICP_DIST = (0.5, 0.05)
ICP_POINTS = 50_000
#: Ways to place the map on the truth (module docstring).
REFINE_MODES = ("none", "poses", "icp")


@dataclasses.dataclass(frozen=True)
class MapMetrics:
    """Dense-map metrics in metres (module docstring).

    Attributes:
        accuracy, completion, chamfer: means of the nearest distances map -> truth, truth ->
            map, and their mean.
        accuracy_median, completion_median: medians of the same distances.
        far: fraction of map points farther than ``FAR_DIST`` from the truth, in [0, 1].
        accuracy_rmse, completion_rmse: RMSE of the distances capped at ``FAR_DIST`` (paper).
        n_map, n_truth: points in the map and in the truth (before sampling).
    """

    accuracy: float
    completion: float
    chamfer: float
    accuracy_median: float
    completion_median: float
    far: float
    accuracy_rmse: float
    completion_rmse: float
    n_map: int
    n_truth: int

    def to_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dict."""
        return dataclasses.asdict(self)


def _cloud(points: Any, name: str) -> FloatArray:
    P = as_float_array(points, name, 3)
    if P.ndim != 2 or len(P) == 0:
        raise ValueError(f"{name}: expected a non-empty (n, 3) array, got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError(f"{name}: non-finite coordinates")
    return P


def voxel_downsample(points: Any, voxel: float = VOXEL) -> FloatArray:
    """One point per occupied voxel of edge ``voxel``: the centroid of its points.

    Args:
        points: (N, 3) finite points.
        voxel: edge length (m), > 0.

    Returns:
        (M, 3) centroids, M <= N, ordered by voxel index.
    """
    P = _cloud(points, "points")
    if not (np.isfinite(voxel) and voxel > 0):
        raise ValueError(f"voxel: must be finite and > 0, got {voxel}")
    key = np.floor(P / voxel).astype(np.int64)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    sums = np.stack([np.bincount(inv, P[:, a], len(counts)) for a in range(3)], axis=1)
    return sums / counts[:, None]


def truth_from_rgbd(
    sequence: Any,
    step: int = FRAME_STEP,
    voxel: float = VOXEL,
    t_range: tuple[float, float] | None = None,
) -> FloatArray:
    """True points of an RGB-D sequence: depth of every ``step``-th frame, in the world.

    ``X_W = T_WC_gt · (z(u, v) K⁻¹ [u, v, 1])`` for every valid depth pixel (z > 0), then
    :func:`voxel_downsample` (each frame first, then the union).

    Args:
        sequence: a ``mslam.datasets.FrameSequence`` with ``K``, depth and ground-truth poses.
        step: frame stride, >= 1.
        voxel: voxel edge (m).
        t_range: ``(t0, t1)``: only frames with ``t0 <= timestamp <= t1``; None for all.

    Returns:
        (P, 3) world points.

    Raises:
        ValueError: without intrinsics, depth or ground truth, or when no frame has depth.
    """
    if sequence.K is None or not sequence.has_depth:
        raise ValueError(f"{sequence.name}: needs intrinsics and depth images")
    if int(step) < 1:
        raise ValueError(f"step: must be >= 1, got {step}")
    stamps = np.asarray(sequence.timestamps, dtype=np.float64)
    parts = []
    for i in range(0, len(sequence), int(step)):
        if t_range is not None and not (t_range[0] <= stamps[i] <= t_range[1]):
            continue
        f = sequence[i]
        if f.T_WC is None or f.depth is None:
            continue
        valid = f.depth > 0
        if not valid.any():
            continue
        X_C = (f.depth[..., None] * camera_rays(sequence.K, *f.shape))[valid]
        parts.append(voxel_downsample(sim3.act(f.T_WC, X_C), voxel))
    if not parts:
        raise ValueError(f"{sequence.name}: no frame with depth and a ground-truth pose")
    return voxel_downsample(np.concatenate(parts), voxel)


def align_points(points: Any, R: FloatArray, t: FloatArray, s: float) -> FloatArray:
    """``s R x + t`` for every row ``x`` of ``points`` (N, 3); the transform of an ATE fit."""
    return s * _cloud(points, "points") @ np.asarray(R).T + np.asarray(t)


def orientation_disagreement(R: FloatArray, est_quats: Any, gt_quats: Any) -> float:
    """Angle (degrees) between an alignment rotation and the one the orientations imply.

    ``R_o = argmin_R Σ_i ‖R R_est,i − R_gt,i‖²_F`` (the chordal mean of ``R_gt,i R_est,iᵀ``,
    projected onto SO(3) by SVD); returns the angle of ``R_oᵀ R``. A few tenths of a degree
    means positions and orientations agree on the alignment; several degrees mean the
    positions do not determine the rotation (or the estimate's orientations drift).

    Args:
        R: (3, 3) alignment rotation (``AteResult.rotation``).
        est_quats, gt_quats: (n, 4) associated orientations ``[qx, qy, qz, qw]``.
    """
    M = np.einsum(
        "nij,nkj->ik", so3.to_matrix(np.asarray(gt_quats)), so3.to_matrix(np.asarray(est_quats))
    )
    U, _, Vt = np.linalg.svd(M)
    R_o = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return float(angle_deg(R_o.T @ np.asarray(R)))


def pose_alignment(
    P_est: FloatArray, q_est: Any, P_gt: FloatArray, q_gt: Any, s0: float
) -> tuple[FloatArray, FloatArray, float]:
    """Sim(3) ``(R, t, s)`` fitted to the cameras' positions *and* orientations.

    Umeyama on each camera's centre and the tips of its three axes, at a lever of ``L`` metres
    in the truth (the RMS spread of the true centres, at least 0.1 m) and ``L / s0`` in the
    estimate's units (``s0``: the positions-only scale). On a nearly straight path the positions
    leave the rotation about the path's axis undetermined (``orientation_disagreement`` of
    several degrees); the axes pin it, so a map moved by this transform sits where its own
    cameras say it does.

    Args:
        P_est, P_gt: (n, 3) associated camera centres; q_est, q_gt: (n, 4) ``[qx, qy, qz, qw]``.
        s0: the positions-only Sim(3) scale.
    """
    P_est, P_gt = np.asarray(P_est, np.float64), np.asarray(P_gt, np.float64)
    L = max(float(np.sqrt(np.mean(np.sum((P_gt - P_gt.mean(0)) ** 2, axis=1)))), 0.1)
    R_e, R_g = so3.to_matrix(np.asarray(q_est)), so3.to_matrix(np.asarray(q_gt))
    src = [P_est] + [P_est + (L / s0) * R_e[:, :, k] for k in range(3)]
    dst = [P_gt] + [P_gt + L * R_g[:, :, k] for k in range(3)]
    from mslam.evaluate import umeyama

    return umeyama(np.concatenate(src), np.concatenate(dst), with_scale=True)


def icp_refine(
    map_points: Any,
    truth_points: Any,
    R: FloatArray,
    t: FloatArray,
    s: float,
    seed: int = 0,
) -> tuple[FloatArray, FloatArray, float]:
    """Rigid point-to-point ICP of the scaled map onto the truth, started from ``(R, t, s)``.

    The scale ``s`` stays the trajectory's: with a free scale, ICP on a noisy map shrinks it
    (a smaller map has smaller distances; measured 2026-11-26 on a 7-Scenes RGB-only run: scale
    4.80 -> 3.49, completion 11 -> 23 cm). Each of ``ICP_ITERS`` iterations pairs every one of
    ``ICP_POINTS`` map points (a seeded draw) with its nearest true point, keeps the pairs
    closer than the iteration's distance (``ICP_DIST[0]`` down to ``ICP_DIST[1]``, geometric)
    and refits ``(R, t)`` on them with ``mslam.evaluate.umeyama`` (no scale).

    Args:
        map_points: (N, 3) the map in its own frame; truth_points: (P, 3).
        R, t, s: the initial transform ``x -> s R x + t``.
        seed: seed of the point draw.

    Returns:
        the refined ``(R (3, 3), t (3,), s)``, ``s`` unchanged.

    Raises:
        ValueError: when an iteration keeps fewer than 3 pairs (no overlap to register).
    """
    from mslam.evaluate import umeyama

    M = float(s) * _sample(
        _cloud(map_points, "map_points"), ICP_POINTS, np.random.default_rng(seed)
    )
    T = _cloud(truth_points, "truth_points")
    tree = cKDTree(T)
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    d0, d1 = ICP_DIST
    for it in range(ICP_ITERS):
        cut = d0 * (d1 / d0) ** (it / (ICP_ITERS - 1))
        dist, j = tree.query(align_points(M, R, t, 1.0), k=1)
        ok = dist < cut
        if ok.sum() < 3:
            raise ValueError(f"map_points: ICP found {int(ok.sum())} pairs within {cut:.3f} m")
        R, t, _ = umeyama(M[ok], T[j[ok]], with_scale=False)
    return R, t, float(s)


def _sample(P: FloatArray, n: int, rng: np.random.Generator) -> FloatArray:
    return P if len(P) <= n else P[rng.choice(len(P), n, replace=False)]


def map_metrics(
    map_points: Any,
    truth_points: Any,
    max_points: int = MAX_POINTS,
    seed: int = 0,
    far_dist: float = FAR_DIST,
) -> MapMetrics:
    """Accuracy, completion, chamfer, far fraction and medians of an aligned map.

    Paper: §4.2, Table 3 (see the module docstring for the means and the capped RMSE).

    Args:
        map_points: (N, 3) the estimate, already in the truth's frame.
        truth_points: (P, 3) the truth.
        max_points: each direction averages over at most this many randomly drawn points.
        seed: seed of the draw.
        far_dist: distance (m) beyond which a map point is "far"; also the RMSE cap.

    Returns:
        :class:`MapMetrics`.

    Raises:
        ValueError: on empty or non-finite clouds, ``max_points < 1`` or ``far_dist <= 0``.
    """
    M = _cloud(map_points, "map_points")
    T = _cloud(truth_points, "truth_points")
    if int(max_points) < 1:
        raise ValueError(f"max_points: must be >= 1, got {max_points}")
    if not (np.isfinite(far_dist) and far_dist > 0):
        raise ValueError(f"far_dist: must be finite and > 0, got {far_dist}")
    rng = np.random.default_rng(seed)
    M_s, T_s = _sample(M, int(max_points), rng), _sample(T, int(max_points), rng)
    d_acc, _ = cKDTree(T).query(M_s, k=1)
    d_comp, _ = cKDTree(M).query(T_s, k=1)
    acc, comp = float(np.mean(d_acc)), float(np.mean(d_comp))
    return MapMetrics(
        accuracy=acc,
        completion=comp,
        chamfer=0.5 * (acc + comp),
        accuracy_median=float(np.median(d_acc)),
        completion_median=float(np.median(d_comp)),
        far=float(np.mean(d_acc > far_dist)),
        accuracy_rmse=float(np.sqrt(np.mean(np.minimum(d_acc, far_dist) ** 2))),
        completion_rmse=float(np.sqrt(np.mean(np.minimum(d_comp, far_dist) ** 2))),
        n_map=len(M),
        n_truth=len(T),
    )


def evaluate_map(
    map_points: Any,
    est_stamps: Any,
    est_poses: Any,
    gt_stamps: Any,
    gt_poses: Any,
    truth_points: Any,
    align: str = "sim3",
    max_diff: float = 0.01,
    refine: str = "none",
    seed: int = 0,
) -> tuple[MapMetrics, Any, dict[str, Any]]:
    """Align the map with the trajectory's ATE transform (or the cameras' poses, or ICP after
    it), then :func:`map_metrics`.

    Args:
        map_points: (N, 3) the run's map in its own world frame.
        est_stamps, est_poses, gt_stamps, gt_poses: as ``mslam.evaluate.ate``; poses with
            quaternions (``(n, 7)`` or ``(n, 8)``) also give :func:`orientation_disagreement`.
        truth_points: (P, 3) the truth in the ground truth's world frame.
        align: "sim3" (default), "se3" or "none"; the same transform moves the map.
        max_diff: association tolerance (s).
        refine: "none", "poses" (:func:`pose_alignment`: positions and orientations) or
            "icp" (:func:`icp_refine` from the trajectory's transform, whose scale it keeps).
        seed: seed of the point draws.

    Returns:
        (:class:`MapMetrics`, the ``mslam.evaluate.AteResult`` of the trajectory, a dict
        ``alignment`` describing the map's transform: ``refine``, ``scale``,
        ``rotation_vs_orientations_deg`` (or None), and with ICP ``icp_rotation_deg`` and
        ``icp_centroid_shift_m``, the correction ICP made).
    """
    from mslam.evaluate import ate

    if refine not in REFINE_MODES:
        raise ValueError(f"refine: expected one of {REFINE_MODES}, got {refine!r}")
    res = ate(est_stamps, est_poses, gt_stamps, gt_poses, align, max_diff)
    R, t, s = res.rotation, res.translation, res.scale
    info: dict[str, Any] = {"refine": refine, "rotation_vs_orientations_deg": None}
    e, g = np.asarray(est_poses), np.asarray(gt_poses)
    if e.ndim == 2 and g.ndim == 2 and min(e.shape[1], g.shape[1]) >= 7:
        q_e, q_g = e[res.est_index, 3:7], g[res.gt_index, 3:7]
        info["rotation_vs_orientations_deg"] = orientation_disagreement(R, q_e, q_g)
    if refine == "poses":
        if info["rotation_vs_orientations_deg"] is None:
            raise ValueError("refine 'poses': both trajectories need orientations")
        P_e, P_g = e[res.est_index, :3], g[res.gt_index, :3]
        R, t, s = pose_alignment(P_e, e[res.est_index, 3:7], P_g, g[res.gt_index, 3:7], s)
        info["rotation_vs_orientations_deg_after"] = orientation_disagreement(
            R, e[res.est_index, 3:7], g[res.gt_index, 3:7]
        )
    if refine == "icp":
        R2, t2, s2 = icp_refine(map_points, truth_points, R, t, s, seed)
        info["icp_rotation_deg"] = float(angle_deg(R2.T @ R))
        c_traj = np.mean(align_points(map_points, R, t, s), axis=0)
        c_icp = np.mean(align_points(map_points, R2, t2, s2), axis=0)
        info["icp_centroid_shift_m"] = float(np.linalg.norm(c_icp - c_traj))
        R, t, s = R2, t2, s2
    info["scale"] = float(s)
    moved = align_points(map_points, R, t, s)
    return map_metrics(moved, truth_points, seed=seed), res, info
