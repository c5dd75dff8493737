"""Paper §4 (evaluation) — absolute trajectory error and dense-reconstruction metrics (docs/upstream.md §12).

The paper scores trajectories with ``evo_ape tum <gt> <estimate> -as``: the ATE RMSE of the
translation part after a Umeyama Sim(3) alignment of *all* associated poses, with evo's default
timestamp association (nearest stamp within 0.01 s). This module reproduces evo's numbers
(RMSE, mean, median, max, scale, number of matched pairs) to 1e-6 on evo's own test data
(``tests/reference/test_evaluate.py``), without using evo:

1. :func:`associate` — evo's ``matching_time_indices`` as driven by ``associate_trajectories``:
   the *shorter* trajectory's stamps are each matched to the nearest stamp (first minimum) of the
   longer one, kept when ``|dt| <= max_diff``. A longer stamp may be used more than once.
2. :func:`umeyama` — the closed-form least-squares similarity (Umeyama 1991) ``dst ≈ s R src + t``.
3. :func:`ate` — aligned positions ``s R p_est + t``, errors ``‖p_aligned − p_gt‖``, statistics.

Dense geometry (paper §4.2, Table 3): :func:`reconstruction_metrics` — accuracy, completion and
chamfer with the 0.5 m distance cap.

Public names, in reading order: AteResult, associate, umeyama, ate, reconstruction_metrics.

Upstream: evo (MichaelGrupp/evo) core/sync.py::associate_trajectories and matching_time_indices,
core/geometry.py::umeyama_alignment, core/metrics.py::APE (translation_part) — re-implemented
from their documented behaviour, no GPL code copied. MASt3R-SLAM scripts/eval_*.sh.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mslam_ref.conventions import FloatArray, IntArray, as_float_array

__all__ = ["AteResult", "associate", "ate", "reconstruction_metrics", "umeyama"]

#: Relative rank tolerance of :func:`umeyama`: the second singular value of the (unit-scaled)
#: cross-covariance must exceed this fraction of the first (collinear or static otherwise).
_REL_RANK_TOL = 1e-10
#: Relative spread tolerance of :func:`umeyama`: each point set's RMS distance from its
#: centroid must exceed this fraction of its largest coordinate. Rounding leaves a static set
#: (a camera that only rotates) a spread of ~1e-16 of its magnitude, which the rank test alone
#: compares with itself and accepts: the ground truth of ``synthetic:rotation:30`` then aligns
#: with scale ~1e-31 and an ATE of ~1e-16 m (measured 2026-11-27).
_REL_SPREAD_TOL = 1e-12

#: Alignment modes of :func:`ate` (evo: ``-as``, ``-a``, no flag).
ALIGN_MODES = ("sim3", "se3", "none")


@dataclasses.dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error (translation part) after alignment; metres.

    Attributes:
        rmse, mean, median, max: statistics of ``errors``.
        scale: Sim(3) alignment scale (1.0 for ``se3`` and ``none``).
        matched: number of associated pose pairs (evo's "matched").
        n_est: number of poses in the estimate.
        aligned_positions: (matched, 3) aligned estimate positions ``s R p + t``.
        errors: (matched,) per-pair translation errors.
        gt_positions: (matched, 3) the associated ground-truth positions.
        rotation: (3, 3) R of the alignment; translation: (3,) t of the alignment.
        est_index, gt_index: (matched,) indices of the pairs in the input arrays.
    """

    rmse: float
    mean: float
    median: float
    max: float
    scale: float
    matched: int
    n_est: int
    aligned_positions: FloatArray
    errors: FloatArray
    gt_positions: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    rotation: FloatArray = dataclasses.field(default_factory=lambda: np.eye(3))
    translation: FloatArray = dataclasses.field(default_factory=lambda: np.zeros(3))
    est_index: IntArray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    gt_index: IntArray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))

    def to_dict(self) -> dict[str, Any]:
        """The scalar results as a JSON-ready dict (keys of ``mslam eval`` / summary.json)."""
        return {
            "ate_rmse": self.rmse,
            "ate_mean": self.mean,
            "ate_median": self.median,
            "ate_max": self.max,
            "scale": self.scale,
            "matched": self.matched,
            "n_est": self.n_est,
            "reference_spread": self.reference_spread,
        }

    @property
    def reference_spread(self) -> float:
        """RMS distance of the associated ground-truth positions from their centroid (metres):
        how far the path reaches, which bounds how well the alignment's scale is determined."""
        g = np.asarray(self.gt_positions, np.float64).reshape(-1, 3)
        return float(np.sqrt(np.mean(np.sum((g - g.mean(0)) ** 2, axis=1)))) if len(g) else 0.0


def _stamps(x: Any, name: str) -> FloatArray:
    arr = as_float_array(x, name)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected shape (n,), got {arr.shape}")
    return arr


def associate(est_stamps: Any, gt_stamps: Any, max_diff: float = 0.01) -> tuple[IntArray, IntArray]:
    """Match estimate and ground-truth stamps exactly as evo does by default.

    Upstream: evo core/sync.py::associate_trajectories (``traj_1`` = reference, ``traj_2`` =
    estimate, offset 0) and ``matching_time_indices``.

    The shorter of the two stamp lists drives (the estimate when the lengths are equal): for
    each of its stamps ``a`` in order, ``j = argmin_j |b_j − a|`` over the longer list (the first
    index on ties, unsorted lists allowed) and the pair is kept when ``|b_j − a| <= max_diff``.

    Args:
        est_stamps: (n_est,) estimate timestamps, seconds.
        gt_stamps: (n_gt,) ground-truth timestamps, seconds.
        max_diff: largest accepted ``|dt|`` (evo's ``t_max_diff``, default 0.01 s).

    Returns:
        est_index, gt_index: (matched,) int64 indices of the pairs, in the driving list's order.

    Raises:
        ValueError: on non-1-D or non-finite stamps, an empty list or a negative ``max_diff``.
    """
    a_est = _stamps(est_stamps, "est_stamps")
    a_gt = _stamps(gt_stamps, "gt_stamps")
    if len(a_est) == 0 or len(a_gt) == 0:
        raise ValueError("est_stamps/gt_stamps: empty trajectory")
    if not (np.isfinite(max_diff) and max_diff >= 0):
        raise ValueError(f"max_diff: must be finite and >= 0, got {max_diff}")
    est_drives = len(a_est) <= len(a_gt)
    short, long = (a_est, a_gt) if est_drives else (a_gt, a_est)
    # Dense |dt| in row chunks (bounded memory); np.argmin returns the first minimum like evo.
    chunk = max(1, 4_000_000 // len(long))
    nearest = np.empty(len(short), np.int64)
    for s0 in range(0, len(short), chunk):
        d = np.abs(long[None, :] - short[s0 : s0 + chunk, None])
        nearest[s0 : s0 + chunk] = np.argmin(d, axis=1)
    keep = np.abs(long[nearest] - short) <= max_diff
    i_short = np.flatnonzero(keep).astype(np.int64)
    i_long = nearest[keep]
    return (i_short, i_long) if est_drives else (i_long, i_short)


def umeyama(
    src: Any, dst: Any, with_scale: bool = True, names: tuple[str, str] = ("src", "dst")
) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares similarity ``dst_i ≈ s R src_i + t`` (Umeyama, PAMI 1991).

    Upstream: evo core/geometry.py::umeyama_alignment.

    ``Σ = (1/n) Σ_i (dst_i − μ_dst)(src_i − μ_src)^T = U D V^T``; ``S = diag(1, 1, ±1)`` with −1
    when ``det U · det V < 0``; ``R = U S V^T``; ``s = tr(D S) / σ²_src`` with
    ``σ²_src = (1/n) Σ ‖src_i − μ_src‖²`` (or 1 without scale); ``t = μ_dst − s R μ_src``.

    Args:
        src: (n, 3) points to move (estimate positions).
        dst: (n, 3) target points (ground truth).
        with_scale: estimate ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).
        names: what the errors call ``src`` and ``dst``.

    Returns:
        R (3, 3), t (3,), s.

    Raises:
        ValueError: on mismatched shapes or a degenerate configuration (either set without
            spread, e.g. a camera that only rotates; covariance rank < 2, e.g. fewer than 3
            points or all points collinear), as evo refuses to align.
    """
    src = as_float_array(src, "src", 3)
    dst = as_float_array(dst, "dst", 3)
    if src.ndim != 2 or src.shape != dst.shape:
        raise ValueError(f"src/dst: expected two (n, 3) arrays, got {src.shape} and {dst.shape}")
    n = len(src)
    if n == 0:
        raise ValueError("src: no points to align")
    # Work on copies scaled to unit magnitude: no overflow for huge coordinates, and every
    # degeneracy test below is relative (no absolute threshold).
    k_s = max(float(np.max(np.abs(src))), np.finfo(float).tiny)
    k_d = max(float(np.max(np.abs(dst))), np.finfo(float).tiny)
    src_n, dst_n = src / k_s, dst / k_d
    mu_s, mu_d = src_n.mean(axis=0), dst_n.mean(axis=0)
    sc, dc = src_n - mu_s, dst_n - mu_d
    var_s = float(np.mean(np.sum(sc * sc, axis=1)))
    var_d = float(np.mean(np.sum(dc * dc, axis=1)))
    for name, var in zip(names, (var_s, var_d), strict=True):
        if not var > _REL_SPREAD_TOL**2:
            raise ValueError(
                f"{name}: degenerate point configuration ({n} points without spread relative "
                "to their magnitude: a static camera, or one that only turned); Umeyama "
                "alignment is not possible"
            )
    cov = dc.T @ sc / n
    U, D, Vt = np.linalg.svd(cov)
    if not (D[0] > 0 and D[1] > _REL_RANK_TOL * D[0]):
        raise ValueError(
            f"{names[0]}: degenerate point configuration ({n} points: static, collinear or "
            "without spread relative to their magnitude); Umeyama alignment is not possible"
        )
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt
    s_n = float(np.sum(D * S) / var_s) if with_scale else k_s / k_d
    s = s_n * k_d / k_s
    t = k_d * (mu_d - s_n * R @ mu_s)
    if not (np.isfinite(s) and s > 0 and np.all(np.isfinite(t))):
        raise ValueError(f"src/dst: alignment not representable (scale {s}); check the units")
    return R, t, s


def _positions(poses: Any, name: str) -> FloatArray:
    """(n, 3) positions from (n, 3), (n, 7) [t, q], (n, 8) Sim(3) or (n, 4, 4)/(n, 3, 4)."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] in ((4, 4), (3, 4)):
        return as_float_array(arr, name)[:, :3, 3]
    if arr.ndim == 2 and arr.shape[1] in (3, 7, 8):
        return as_float_array(arr, name)[:, :3]
    raise ValueError(f"{name}: expected shape (n, 3), (n, 7), (n, 8) or (n, 4, 4), got {arr.shape}")


def ate(
    est_stamps: Any,
    est_poses: Any,
    gt_stamps: Any,
    gt_poses: Any,
    align: str = "sim3",
    max_diff: float = 0.01,
) -> AteResult:
    """Absolute trajectory error of the translation part, as ``evo_ape tum gt est [-a|-as]``.

    Paper: §4 "we report ATE RMSE … with Sim(3) Umeyama alignment" (docs/upstream.md §12.1).
    Upstream: MASt3R-SLAM scripts/eval_*.sh (``evo_ape tum <gt> <traj> -as``).

    ``e_i = ‖s R p_est,i + t − p_gt,j(i)‖`` over all associated pairs (i, j(i)); the alignment
    (R, t, s) is :func:`umeyama` fitted on all pairs. ``rmse = sqrt(mean e²)``.

    Args:
        est_stamps: (n_est,) estimate stamps in seconds, or None together with ``gt_stamps``
            None for association by index (evo's ``kitti`` mode; lengths must be equal).
        est_poses: (n_est, 7) ``[t, q_xyzw]`` (read_tum), (n_est, 8) Sim(3), (n_est, 3)
            positions or (n_est, 4, 4) matrices; only the translations are used.
        gt_stamps: (n_gt,) ground-truth stamps, or None (see ``est_stamps``).
        gt_poses: (n_gt, ...) like ``est_poses``.
        align: "sim3" (evo ``-as``), "se3" (``-a``) or "none".
        max_diff: association tolerance in seconds (evo's default 0.01).

    Returns:
        :class:`AteResult`.

    Raises:
        ValueError: on bad shapes, an unknown ``align``, no associated pair, or a degenerate
            alignment (fewer than 3 non-collinear matched positions).
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"align: expected one of {ALIGN_MODES}, got {align!r}")
    p_est = _positions(est_poses, "est_poses")
    p_gt = _positions(gt_poses, "gt_poses")
    if (est_stamps is None) != (gt_stamps is None):
        raise ValueError("est_stamps/gt_stamps: give both stamp arrays or neither")
    if est_stamps is None:
        if len(p_est) != len(p_gt):
            raise ValueError(
                f"est_poses: index association needs equal lengths, got {len(p_est)} "
                f"estimate and {len(p_gt)} ground-truth poses"
            )
        i_est = i_gt = np.arange(len(p_est), dtype=np.int64)
    else:
        for name, st, p in (("est_stamps", est_stamps, p_est), ("gt_stamps", gt_stamps, p_gt)):
            if np.shape(st) != (len(p),):
                raise ValueError(f"{name}: expected shape ({len(p)},), got {np.shape(st)}")
        for name, st in (("est_stamps", est_stamps), ("gt_stamps", gt_stamps)):
            st = np.asarray(st, dtype=np.float64)
            if len(st) > 1 and np.all(st == st[0]):
                raise ValueError(f"{name}: all {len(st)} timestamps are equal; cannot associate")
        i_est, i_gt = associate(est_stamps, gt_stamps, max_diff)
    if len(i_est) == 0:
        raise ValueError(
            f"est_stamps: no estimate stamp is within max_diff={max_diff} s of a ground-truth stamp"
        )
    src, dst = p_est[i_est], p_gt[i_gt]
    if align == "none":
        R, t, s = np.eye(3), np.zeros(3), 1.0
    else:
        R, t, s = umeyama(src, dst, align == "sim3", ("est_poses", "gt_poses"))
    aligned = s * src @ R.T + t
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.linalg.norm(aligned - dst, axis=1)
        rmse = float(np.sqrt(np.mean(err**2)))
    if not np.isfinite(rmse):
        raise ValueError("est_poses/gt_poses: the errors overflow (coordinates too large)")
    return AteResult(
        rmse=rmse,
        mean=float(np.mean(err)),
        median=float(np.median(err)),
        max=float(np.max(err)),
        scale=float(s),
        matched=len(err),
        n_est=len(p_est),
        aligned_positions=aligned,
        errors=err,
        gt_positions=dst,
        rotation=R,
        translation=t,
        est_index=i_est,
        gt_index=i_gt,
    )


def reconstruction_metrics(
    est_points: Any, ref_points: Any, max_dist: float = 0.5
) -> tuple[float, float, float]:
    """Accuracy, completion and chamfer distance of a point cloud against a reference (metres).

    Paper: §4.2 / Table 3 (docs/upstream.md §12.1): "accuracy = RMSE of the nearest-neighbour distance from
    the estimated points to the reference; completion = RMSE from the reference points to the
    estimate; both with a 0.5 m max-distance threshold; chamfer = (accuracy + completion) / 2".
    Upstream: none (the dense evaluation code is unreleased, issues #84 and #124).

    Decision on the threshold: distances are **truncated** to ``max_dist`` (``min(d, max_dist)``),
    not excluded. Every point still counts, an outlier costs at most ``max_dist`` and the metric
    stays bounded by ``max_dist``; excluding far points instead would let a cloud of stray
    points score a perfect accuracy (and an empty overlap an undefined one).

    ``accuracy = sqrt(mean_i min(d(est_i, ref), max_dist)²)``, likewise ``completion`` with the
    roles swapped; nearest neighbours by ``scipy.spatial.cKDTree``.

    Args:
        est_points: (N, 3) estimated (already aligned) points.
        ref_points: (P, 3) reference points.
        max_dist: the distance cap, > 0 (paper: 0.5 m).

    Returns:
        (accuracy, completion, chamfer).

    Raises:
        ValueError: on empty or non-finite clouds, wrong shapes or a non-positive ``max_dist``.
    """
    est = as_float_array(est_points, "est_points", 3)
    ref = as_float_array(ref_points, "ref_points", 3)
    for name, pts in (("est_points", est), ("ref_points", ref)):
        if pts.ndim != 2 or len(pts) == 0:
            raise ValueError(f"{name}: expected a non-empty (n, 3) array, got {pts.shape}")
    if not (np.isfinite(max_dist) and max_dist > 0):
        raise ValueError(f"max_dist: must be finite and > 0, got {max_dist}")
    d_est, _ = cKDTree(ref).query(est, k=1)
    d_ref, _ = cKDTree(est).query(ref, k=1)
    accuracy = float(np.sqrt(np.mean(np.minimum(d_est, max_dist) ** 2)))
    completion = float(np.sqrt(np.mean(np.minimum(d_ref, max_dist) ** 2)))
    return accuracy, completion, 0.5 * (accuracy + completion)
