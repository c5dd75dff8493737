"""A small incremental reconstruction of one stretch of video, for the self-calibration.

Given point tracks (:mod:`mslam.priors.selfcal_tracks`) and the views of a stretch (every
n-th frame), :func:`reconstruct` builds poses, points and the camera together, refining the
camera as the reconstruction grows, as incremental structure from motion does
(:mod:`mslam.priors.selfcal_ba`):

1. **Two views to start**: the first pair, scanning forward, whose tracks move by at least
   ``START_PARALLAX_PX`` (median) away from their best homography (no rotation of the
   camera explains them) and show a median triangulation angle of at least ``START_DEG``
   under the essential matrix's pose (RANSAC at ``RANSAC_PX`` pixels, at the guessed focal
   length and no lens). Without the homography test a wobbling camera started from a pair
   that its turn explained, and the stretch's focal length ended 15 % long (the 7-Scenes
   kitchen re-rendered at 50°: ×1.42 against ×1.24; with it ×1.233, 2026-11-28).
2. **Every other view by PnP** (RANSAC at ``RANSAC_PX``) on the points seen so far, in order
   away from the starting pair, each followed by the triangulation of the tracks that two
   registered views now see at ``TRIANGULATE_DEG`` or more. Every ``REFINE_EVERY`` views a
   bundle adjustment with the camera free tidies up and drops tracks off by more than
   ``PRUNE_PX``; new views and points then use the refined camera.
3. **The camera settled**: a bundle adjustment of everything, tracks whose residual exceeds
   3 robust standard deviations dropped, and a final adjustment.

Returns None where no starting pair exists (too little parallax: a camera that only turns, or
stands) or fewer than ``MIN_VIEWS_SHARE`` of the views register.

Public names, in reading order:
    START_DEG, TRIANGULATE_DEG, Reconstruction, reconstruct
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mslam.datasets.images import centre_scale
from mslam.priors.selfcal_ba import Problem, Solution, bundle_adjust, camera_covariance, residuals
from mslam.priors.selfcal_tracks import Tracks
from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["START_DEG", "TRIANGULATE_DEG", "Reconstruction", "reconstruct"]

#: Least median triangulation angle of the starting pair, and of a new point (degrees).
START_DEG = 3.0
#: Least median homography parallax of the starting pair (pixels).
START_PARALLAX_PX = 1.0
TRIANGULATE_DEG = 1.5
RANSAC_PX = 1.0
MIN_COMMON = 50
MIN_PNP = 15
REFINE_EVERY = 4
PRUNE_PX = 3.0
MIN_VIEWS_SHARE = 0.8


@dataclass(frozen=True)
class Reconstruction:
    """The stretch's reconstruction with its own camera.

    Attributes:
        F: focal length over the half diagonal. k: radial coefficient (forward model,
            half-diagonal units; :mod:`mslam.priors.selfcal_ba`).
        cov: (2, 2) covariance of ``(log F, k)`` scaled by the residuals' robust variance.
        sigma_px: robust standard deviation of the final residuals (pixels).
        views: views registered. views_total: views of the stretch. points: points kept.
    """

    F: float
    k: float
    cov: FloatArray
    sigma_px: float
    views: int
    views_total: int
    points: int


class _Window:
    """Track table of one stretch: ``uv[v, j]`` (pixels, NaN where track j misses view v)."""

    def __init__(self, tracks: Tracks, views: IntArray, F0: float) -> None:
        W, H = tracks.size
        self.c, self.s = centre_scale(W, H)
        pos = np.full(int(tracks.frame.max()) + 1, -1)
        pos[views] = np.arange(len(views))
        keep = pos[tracks.frame] >= 0
        ids, col = np.unique(tracks.track[keep], return_inverse=True)
        self.uv = np.full((len(views), len(ids), 2), np.nan)
        self.uv[pos[tracks.frame[keep]], col] = tracks.uv[keep]
        self.R = np.tile(np.eye(3), (len(views), 1, 1))
        self.t = np.zeros((len(views), 3))
        self.reg = np.zeros(len(views), bool)
        self.X = np.full((len(ids), 3), np.nan)
        self.F, self.k = F0, 0.0

    def rays(self, v: int, cols: IntArray) -> FloatArray:
        """Normalised image points (N, 2) of tracks ``cols`` in view ``v`` at the guess."""
        return self.normalise(self.uv[v, cols])

    def normalise(self, uv: FloatArray) -> FloatArray:
        """Pixels (..., 2) to normalised image points under the current camera (the forward
        lens model inverted by fixed-point iteration)."""
        x_d = (uv - self.c) / self.s
        x_u = x_d.copy()
        for _ in range(5):
            x_u = x_d / (1.0 + self.k * (x_u * x_u).sum(-1, keepdims=True))
        return x_u / self.F

    def seen(self, v: int) -> np.ndarray:
        return ~np.isnan(self.uv[v, :, 0])


def _angles(w: _Window, a: IntArray, b: IntArray, X: FloatArray) -> FloatArray:
    """Angle (degrees) at points X (N, 3) between the centres of views a and b (N,)."""
    ca = -np.einsum("nji,nj->ni", w.R[a], w.t[a])
    cb = -np.einsum("nji,nj->ni", w.R[b], w.t[b])
    u, v = X - ca, X - cb
    cos = (u * v).sum(1) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _triangulate(w: _Window, a: IntArray, b: IntArray, cols: IntArray) -> FloatArray:
    """Linear triangulation (N, 3) of tracks ``cols`` from views a and b (N,) each."""
    xa, xb = w.normalise(w.uv[a, cols]), w.normalise(w.uv[b, cols])
    Pa = np.concatenate([w.R[a], w.t[a][:, :, None]], 2)
    Pb = np.concatenate([w.R[b], w.t[b][:, :, None]], 2)
    A = np.stack([xa[:, :1] * Pa[:, 2] - Pa[:, 0], xa[:, 1:] * Pa[:, 2] - Pa[:, 1],
                  xb[:, :1] * Pb[:, 2] - Pb[:, 0], xb[:, 1:] * Pb[:, 2] - Pb[:, 1]], 1)  # fmt: skip
    h = np.linalg.svd(A)[2][:, -1]
    return h[:, :3] / np.where(np.abs(h[:, 3:]) > 1e-12, h[:, 3:], 1e-12)


def _add_points(w: _Window) -> None:
    """Triangulate every track without a point that two registered views see, from its first
    and last registered view, where the angle reaches ``TRIANGULATE_DEG`` in front of both."""
    seen = ~np.isnan(w.uv[:, :, 0]) & w.reg[:, None]
    cols = np.nonzero((seen.sum(0) >= 2) & np.isnan(w.X[:, 0]))[0]
    if not len(cols):
        return
    a = seen[:, cols].argmax(0)
    b = len(w.reg) - 1 - seen[::-1, cols].argmax(0)
    X = _triangulate(w, a, b, cols)
    za = np.einsum("nij,nj->ni", w.R[a], X)[:, 2] + w.t[a, 2]
    zb = np.einsum("nij,nj->ni", w.R[b], X)[:, 2] + w.t[b, 2]
    ok = np.isfinite(X).all(1) & (za > 0) & (zb > 0)
    ok[ok] = _angles(w, a[ok], b[ok], X[ok]) >= TRIANGULATE_DEG
    w.X[cols[ok]] = X[ok]


def _homography_parallax(uv_a: FloatArray, uv_b: FloatArray) -> float:
    """Median distance (pixels) of ``uv_b`` from ``uv_a`` moved by their best homography:
    the flow that no rotation of the camera (and no plane) explains."""
    Hm, _ = cv2.findHomography(uv_a, uv_b, cv2.RANSAC, RANSAC_PX)
    if Hm is None:
        return 0.0
    p = np.c_[uv_a, np.ones(len(uv_a))] @ Hm.T
    return float(np.median(np.linalg.norm(p[:, :2] / p[:, 2:] - uv_b, axis=1)))


def _start(w: _Window) -> bool:
    """Fix the starting pair (module docstring, step 1); False where none exists."""
    nv = len(w.reg)
    px = RANSAC_PX / (w.s * w.F)
    for a in range(nv):
        for b in range(a + 1, nv):
            cols = np.nonzero(w.seen(a) & w.seen(b))[0]
            if len(cols) < MIN_COMMON:
                break
            if _homography_parallax(w.uv[a, cols], w.uv[b, cols]) < START_PARALLAX_PX:
                continue  # a rotation (or a plane): the essential matrix's pose is noise
            xa, xb = w.rays(a, cols), w.rays(b, cols)
            E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), cv2.RANSAC, 0.999, px)
            if E is None or E.shape != (3, 3):
                continue
            _, R, t, mask = cv2.recoverPose(E, xa, xb, np.eye(3), mask=mask)
            inl = mask.ravel() > 0
            if inl.sum() < MIN_COMMON:
                continue
            w.R[b], w.t[b] = R, t.ravel()
            X = _triangulate(w, np.full(inl.sum(), a), np.full(inl.sum(), b), cols[inl])
            if np.median(_angles(w, np.full(len(X), a), np.full(len(X), b), X)) >= START_DEG:
                w.reg[[a, b]] = True
                _add_points(w)
                return True
            w.R[b], w.t[b] = np.eye(3), np.zeros(3)
    return False


def _problem(w: _Window) -> tuple[Problem, IntArray, IntArray]:
    """Observations of the registered views' points: the problem, the registered views (V,)
    and the tracks of the points (P,)."""
    views = np.nonzero(w.reg)[0]
    cols = np.nonzero(~np.isnan(w.X[:, 0]))[0]
    seen = ~np.isnan(w.uv[np.ix_(views, cols)][:, :, 0])
    vi, pj = np.nonzero(seen)
    return Problem(vi, pj, w.uv[views[vi], cols[pj]], w.c, w.s), views, cols


def _adjust(w: _Window, camera: bool, F: float, k: float, prune: float | None, iters: int):
    """Bundle-adjust the registered views and points; drop the tracks of points behind a view
    or with a residual above ``prune`` pixels. Returns ``(solution, problem, views, cols)``."""
    p, views, cols = _problem(w)
    x0 = Solution(w.R[views], w.t[views], w.X[cols], F, k)
    _, X_c, _ = residuals(p, x0)
    front = X_c[:, 2] > 0
    w.X[cols[np.unique(p.point[~front])]] = np.nan
    p, views, cols = _problem(w)
    x, _ = bundle_adjust(p, Solution(w.R[views], w.t[views], w.X[cols], F, k),
                         np.array([0]), camera, iters)  # fmt: skip
    w.R[views], w.t[views], w.X[cols] = x.R, x.t, x.X
    w.F, w.k = x.F, x.k
    if prune is not None:
        res = np.linalg.norm(residuals(p, x)[0], axis=1)
        w.X[cols[np.unique(p.point[res > prune])]] = np.nan
    return x, p


def _register(w: _Window, v: int) -> bool:
    """Pose of view ``v`` by PnP on the points it sees (module docstring, step 2)."""
    cols = np.nonzero(w.seen(v) & ~np.isnan(w.X[:, 0]))[0]
    if len(cols) < MIN_PNP:
        return False
    reg = np.nonzero(w.reg)[0]
    near = reg[np.argmin(np.abs(reg - v))]
    rvec = cv2.Rodrigues(w.R[near])[0]
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        w.X[cols], w.rays(v, cols), np.eye(3), None, rvec, w.t[near].reshape(3, 1).copy(),
        True, 200, RANSAC_PX / (w.s * w.F), 0.999, flags=cv2.SOLVEPNP_ITERATIVE,
    )  # fmt: skip
    if not ok or inl is None or len(inl) < MIN_PNP:
        return False
    w.R[v], w.t[v], w.reg[v] = cv2.Rodrigues(rvec)[0], tvec.ravel(), True
    return True


def _grow(w: _Window) -> None:
    """Register views outward from the starting pair until none registers."""
    added = 0
    while True:
        reg = np.nonzero(w.reg)[0]
        lo, hi = reg.min(), reg.max()
        gaps = [v for v in range(lo + 1, hi) if not w.reg[v]]
        for v in gaps + [u for u in (lo - 1, hi + 1) if 0 <= u < len(w.reg)]:
            if _register(w, v):
                _add_points(w)
                added += 1
                if added % REFINE_EVERY == 0:
                    _adjust(w, True, w.F, w.k, PRUNE_PX, 5)
                break
        else:
            return


def reconstruct(tracks: Tracks, views: IntArray, F0: float) -> Reconstruction | None:
    """Poses, points and the camera of one stretch (module docstring): ``tracks`` of its
    frames, ``views`` (V,) the frame positions used as views, ``F0`` the guessed focal length
    over the half diagonal."""
    w = _Window(tracks, np.asarray(views), F0)
    if not _start(w):
        return None
    _grow(w)
    if w.reg.sum() < MIN_VIEWS_SHARE * len(views):
        return None
    _adjust(w, True, w.F, w.k, PRUNE_PX, 10)
    x, p = _adjust(w, True, w.F, w.k, None, 30)
    sigma = 1.4826 * float(np.median(np.linalg.norm(residuals(p, x)[0], axis=1)))
    x, p = _adjust(w, True, x.F, x.k, max(3.0 * sigma, 0.5), 30)
    x, p = _adjust(w, True, x.F, x.k, None, 30)
    res = np.linalg.norm(residuals(p, x)[0], axis=1)
    sigma = 1.4826 * float(np.median(res))
    cov = camera_covariance(p, x, np.array([0])) * sigma**2
    return Reconstruction(x.F, x.k, cov, sigma, int(w.reg.sum()), len(views), len(x.X))
