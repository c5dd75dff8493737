"""The RGB-D prior's relative pose: RANSAC PnP, point-to-plane ICP, and the check between them.

``mslam.priors.rgbd.RGBDPrior.relative_pose`` matches features between two images, lifts j's
keypoints with j's depth and calls :func:`pnp` (camera j → camera i from 3-D/2-D
correspondences), refines the result with :func:`refine_icp` (j's depth points onto i's
depth map) and keeps the refinement only if :func:`icp_agrees`. ``cfg`` is the prior's
``RGBDPriorConfig``.

:func:`consistency` then checks the posed pointmap of j against i's depth for ``C_ji``.

Public names, in reading order: pnp, normals_at, icp_target, icp_sample, refine_icp, icp_agrees,
consistency.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import backproject, strided_pixels

__all__ = [
    "consistency",
    "icp_agrees",
    "icp_sample",
    "icp_target",
    "normals_at",
    "pnp",
    "refine_icp",
]


def pnp(
    obj: FloatArray, img: FloatArray, K: FloatArray, flags: int, cfg: Any
) -> tuple[FloatArray, int]:
    """RANSAC PnP with ``flags`` + LM refinement, then a sanity check of the result.

    EPnP inside RANSAC occasionally returns a degenerate hypothesis (translations of
    ~1e13 m whose "inliers" are points projected to infinity); such a pose, or one that
    puts inliers behind camera i, moves them by more than ``max_translation``, or whose
    refined inliers do not reproject within ``ransac_px``, is reported as a failure
    (0 inliers) so that the caller can fall back to another solver.
    """
    try:
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, K, None, iterationsCount=cfg.ransac_iters,
            reprojectionError=cfg.ransac_px, confidence=0.999, flags=flags,
        )  # fmt: skip
    except cv2.error:
        return sim3.identity(), 0
    if not found or inl is None or len(inl) < cfg.min_inliers:
        return sim3.identity(), 0
    inl = inl.ravel()
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return sim3.identity(), 0
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    w = np.asarray(rvec, np.float64).ravel()  # the rotation vector (3,)
    R, t = so3.to_matrix(so3.exp(w)), tvec.ravel()
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return sim3.identity(), 0
    if np.linalg.norm(t) > cfg.max_translation:
        return sim3.identity(), 0
    Xi = obj[inl] @ R.T + t
    if np.any(Xi[:, 2] <= 1e-3):
        return sim3.identity(), 0
    uv = Xi[:, :2] / Xi[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    err = np.linalg.norm(uv - img[inl], axis=1)
    n = int(np.sum(err <= cfg.ransac_px))
    if n < cfg.min_inliers:
        return sim3.identity(), 0
    return np.concatenate([t, so3.exp(w), [1.0]]), n


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Column-wise ``a × b`` of (3, n) arrays, written out (np.cross is several times slower)."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def normals_at(
    Y: FloatArray, has_normal: np.ndarray, W: int, flat: np.ndarray
) -> tuple[FloatArray, np.ndarray]:
    """Unit normals of a pointmap at some pixels, from central differences, and their validity.

    ``n = du × dv`` with ``du = Y(u+1, v) - Y(u-1, v)`` and ``dv = Y(u, v+1) - Y(u, v-1)``,
    valid where ``has_normal`` (from :func:`icp_target`) and ``|n| > 1e-12``. ICP needs
    normals only where j's points land, a few thousand pixels: computing them there instead
    of over the whole image saved 6 ms a frame at 512x384.

    Args:
        Y: (3, H·W) points, one row per coordinate, pixels row-major.
        has_normal: (H·W,) bool, interior pixels that have depth and so do their 4 neighbours.
        W: image width.
        flat: (n,) row-major pixel indices in [0, H·W).

    Returns:
        N: (3, n) unit normals (zero where not valid); ok: (n,) bool.
    """
    ok = has_normal.take(flat)
    c = np.where(ok, flat, W + 1)  # an interior pixel keeps the neighbours in range
    # np.take: several times faster than fancy indexing for these gathers.
    n = _cross(
        np.take(Y, c + 1, axis=1) - np.take(Y, c - 1, axis=1),
        np.take(Y, c + W, axis=1) - np.take(Y, c - W, axis=1),
    )
    norm = np.sqrt(np.einsum("kn,kn->n", n, n))
    ok &= norm > 1e-12
    return n * np.where(ok, 1.0 / np.maximum(norm, 1e-12), 0.0), ok


def icp_target(
    depth_i: FloatArray, K_i: FloatArray, Y: FloatArray | None = None
) -> tuple[FloatArray, np.ndarray]:
    """What ICP needs of frame i, the same for every frame registered to it.

    Returns:
        Y_i: (3, H·W) points, one row per coordinate, pixels row-major (gathering a few
            thousand of them is fast); ``RGBDPrior`` passes the (H, W, 3) points it already
            has as ``Y``. ICP reads them only where ``has_normal``, so the points of a
            filled depth map serve as well.
        has_normal: (H·W,) bool, interior pixels whose depth and 4 neighbours' depths are
            valid (> 0): where :func:`normals_at` can take central differences.
    """
    if Y is None:
        Y = backproject(depth_i, K_i)
    H, W = depth_i.shape
    v = depth_i > 0
    has = np.zeros((H, W), bool)
    if H >= 3 and W >= 3:
        has[1:-1, 1:-1] = v[1:-1, 1:-1] & v[1:-1, 2:] & v[1:-1, :-2] & v[2:, 1:-1] & v[:-2, 1:-1]
    return np.ascontiguousarray(Y.reshape(-1, 3).T), has.reshape(-1)


def icp_sample(valid: np.ndarray, n_points: int) -> np.ndarray:
    """Pixels of j that take part in ICP: the valid pixels of a regular grid of stride
    ``floor(sqrt(n_valid / n_points))`` (all of them when that is 1).

    ICP is a 6-parameter fit: a few thousand well-spread points determine it as well as every
    pixel, and the cost does not grow with the resolution (at 512x384 every pixel would make
    ICP the prior's largest cost). Returns an (H, W) bool mask.
    """
    stride = max(1, int(np.sqrt(valid.sum() / max(n_points, 1))))
    if stride == 1:
        return valid
    H, W = valid.shape
    return valid & strided_pixels(H, W, stride)


def refine_icp(
    depth_i: FloatArray | None,
    depth_j: FloatArray,
    K_i: FloatArray,
    K_j: FloatArray,
    T_ij: FloatArray,
    cfg: Any,
    target: tuple[FloatArray, np.ndarray] | None = None,
) -> FloatArray:
    """Point-to-plane ICP of j's depth points onto i's depth map, from the PnP pose.

    Projective association (the point of i at the pixel where ``T_ij X_j`` projects),
    normals of i from central differences, Gauss-Newton on a left perturbation
    ``exp([dt, dw]) T``, residual ``n · (P - Y)``, association distance shrinking from
    ``icp_dist`` to ``icp_dist_final``. The PnP pose is kept if too few pixels end up
    associated or the refinement moves it by more than ``icp_max_change``. ``target`` is
    :func:`icp_target` of ``(depth_i, K_i)`` when the caller keeps it (computed here if None).
    """
    if cfg.icp_iters <= 0 or depth_i is None:
        return T_ij
    Ki, Kj = K_i, K_j
    zj, zi = depth_j, depth_i
    vj, uj = np.nonzero(icp_sample(zj > 0, cfg.icp_points))
    if len(vj) < 100:
        return T_ij
    zs = zj[vj, uj]  # j's sampled pixels only: backproject(zj, Kj)[mask], same arithmetic
    Xj = np.stack([(uj - Kj[0, 2]) / Kj[0, 0] * zs, (vj - Kj[1, 2]) / Kj[1, 1] * zs, zs])
    Yi, has_normal = icp_target(zi, Ki) if target is None else target
    H, W = zi.shape
    R, t = so3.to_matrix(T_ij[3:7]), T_ij[:3].copy()
    R0, t0 = R.copy(), t.copy()
    n_it = cfg.icp_iters
    frac = 0.0
    # Points are (3, n) columns throughout: a few thousand of them, where numpy's overhead
    # per call, not arithmetic, is the cost.
    for it in range(n_it):
        a = it / max(n_it - 1, 1)
        dist = cfg.icp_dist ** (1 - a) * cfg.icp_dist_final**a
        P = R @ Xj + t[:, None]
        front = P[2] > 1e-3
        zs = np.where(front, P[2], 1.0)
        u = np.round(Ki[0, 0] * P[0] / zs + Ki[0, 2]).astype(np.int64)
        v = np.round(Ki[1, 1] * P[1] / zs + Ki[1, 2]).astype(np.int64)
        ok = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        flat = np.where(ok, v * W + u, 0)
        N, ok_n = normals_at(Yi, has_normal, W, flat)
        ok &= ok_n
        E = P - np.take(Yi, flat, axis=1)
        ok &= np.sqrt(np.einsum("kn,kn->n", E, E)) < dist
        n_ok = int(ok.sum())
        frac = n_ok / len(ok)
        if n_ok < 50:
            return T_ij
        P, E, N = (a.compress(ok, axis=1) for a in (P, E, N))
        r = np.einsum("kn,kn->n", N, E)
        J = np.concatenate([N, _cross(P, N)])  # (6, m)
        w = 1.0 / np.maximum(1.0, np.abs(r) / (0.25 * dist))  # Huber weights
        Jw = J * w
        try:
            d = np.linalg.solve(Jw @ J.T + 1e-9 * np.eye(6), -(Jw @ r))
        except np.linalg.LinAlgError:
            return T_ij
        dR = cv2.Rodrigues(d[3:])[0]  # so3.to_matrix(so3.exp(.)), without the checks
        R, t = dR @ R, dR @ t + d[:3]
        if np.linalg.norm(d) < 1e-7:
            break
    rot_change = np.linalg.norm(so3.log(so3.from_matrix(R.T @ R0)))
    if (
        frac < cfg.icp_min_frac
        or np.linalg.norm(t - t0) > cfg.icp_max_change
        or rot_change > cfg.icp_max_change
        or not np.all(np.isfinite(t))
    ):
        return T_ij
    return np.concatenate([t, so3.from_matrix(R), [1.0]])


def icp_agrees(
    T_icp: FloatArray, T_pnp: FloatArray, obj: FloatArray, img: FloatArray, K: FloatArray, cfg: Any
) -> FloatArray:
    """``T_icp`` if it still explains the feature matches, else ``T_pnp``.

    Point-to-plane ICP can slide along a dominant plane (a wall, the floor) where the depth
    maps alone do not constrain the motion: on the synthetic loop it moved a 3-frame pose
    by 8 cm while every PnP inlier stopped reprojecting. The refined pose is kept only if
    at least ``icp_min_agree`` of the matches the PnP pose explains (within ``2 ransac_px``,
    which tolerates RGB-to-depth misregistration) are still explained.
    """

    def explained(T: FloatArray) -> int:
        X = sim3.act(T, obj)
        z = np.where(X[:, 2] > 1e-6, X[:, 2], np.nan)
        uv = X[:, :2] / z[:, None] * K[[0, 1], [0, 1]] + K[:2, 2]
        return int(np.sum(np.linalg.norm(uv - img, axis=1) <= 2 * cfg.ransac_px))

    n_pnp = explained(T_pnp)
    return T_icp if explained(T_icp) >= cfg.icp_min_agree * n_pnp else T_pnp


def consistency(
    X_ji: FloatArray,
    C_jj: FloatArray,
    depth_i: FloatArray,
    valid_i: np.ndarray,
    K_i: FloatArray,
    cfg: Any,
) -> FloatArray:
    """``C_ji``: ``C_jj`` pulled towards 1 where j's point disagrees with i's depth at the
    pixel it projects to (by more than ``consistency_tol`` relative), by
    ``inconsistent_factor``, or falls outside image i, by ``covis_factor``.

    ``pointmap.project`` written out for the (H, W) maps (5 ms at 512x384 through the checked
    general function, 3 ms here).

    Args:
        X_ji: (H, W, 3) j's points in camera i. C_jj: (H, W) their confidences.
        depth_i: (H, W) i's depth (0 = invalid); valid_i: (H, W) bool, depth_i > 0.
        K_i: (3, 3) intrinsics of i.
    """
    H, W = depth_i.shape
    z = X_ji[..., 2]
    front = z > 1e-6
    zc = np.where(front, z, 1.0)  # behind camera i: outside, whatever u and v
    u = np.round(K_i[0, 0] * X_ji[..., 0] / zc + K_i[0, 2])
    v = np.round(K_i[1, 1] * X_ji[..., 1] / zc + K_i[1, 2])
    inside = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    at = np.where(inside, v * W + u, 0).astype(np.intp)  # i's pixel, row-major
    zi = depth_i.take(at)
    bad = inside & valid_i.take(at)
    bad &= np.abs(zi - z) > cfg.consistency_tol * np.maximum(zi, 1e-6)
    C = np.where(bad, 1.0 + (C_jj - 1.0) * cfg.inconsistent_factor, C_jj)
    return np.where(inside, C, 1.0 + (C - 1.0) * cfg.covis_factor)
