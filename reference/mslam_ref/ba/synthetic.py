"""Bundle adjustment — small synthetic problems for tests, tutorials and parity checks.

Cameras on a ring look at a cloud of points; every point is seen by several cameras; the
measurements are exact projections plus Gaussian pixel noise, and the initial estimate is the
truth perturbed. Deterministic for a given ``seed``.

``make_forward_problem`` builds the visual-odometry shape instead (the ORB-SLAM KITTI graphs of
cuda-bundle-adjustment): a camera moving forward, every point seen by a run of 2-12 consecutive
views, so the reduced camera system is banded.

Public functions: make_pinhole_problem, make_bal_problem, make_forward_problem.
"""

from __future__ import annotations

import numpy as np

from mslam_ref import se3, so3
from mslam_ref.ba.cameras import bal_residuals, pinhole_residuals
from mslam_ref.ba.problem import BALProblem, PinholeProblem
from mslam_ref.ba.robust import RobustKernel

__all__ = ["make_bal_problem", "make_forward_problem", "make_pinhole_problem"]


def _scene(n_cams: int, n_points: int, views: int, rng: np.random.Generator):
    """Ring of world-to-camera poses looking at the origin, points, observation lists."""
    ang = np.linspace(0.0, 2.0 * np.pi * 0.5, n_cams)
    centres = np.stack(
        [4.0 * np.sin(ang), 0.3 * rng.standard_normal(n_cams), -4.0 * np.cos(ang)], 1
    )
    poses = []
    for c in centres:
        z = -c / np.linalg.norm(c)  # optical axis towards the origin
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R_wc = np.stack([x, np.cross(z, x), z], 1)
        R_cw = R_wc.T
        poses.append(np.r_[-R_cw @ c, so3.from_matrix(R_cw)])
    points = rng.uniform(-1.0, 1.0, (n_points, 3))
    views = min(views, n_cams)
    obs_pt = np.repeat(np.arange(n_points), views)
    obs_cam = np.concatenate([rng.choice(n_cams, views, replace=False) for _ in range(n_points)])
    return np.asarray(poses), points, obs_cam.astype(np.int64), obs_pt.astype(np.int64)


def make_pinhole_problem(
    n_cams: int = 6,
    n_points: int = 40,
    views: int = 3,
    stereo_fraction: float = 0.3,
    noise: float = 0.5,
    perturb: float = 0.02,
    seed: int = 0,
    kernel: RobustKernel | None = None,
) -> tuple[PinholeProblem, PinholeProblem]:
    """A g2o-style SE(3) problem and its ground truth.

    Args:
        n_cams, n_points: M and P.
        views: observations per point.
        stereo_fraction: share of stereo edges.
        noise: pixel noise (std).
        perturb: scale of the pose (rad, m) and point (m) perturbation of the initial estimate.
        seed: RNG seed.
        kernel: robust kernel for both edge types (default none).

    Returns:
        (problem with the perturbed initial estimate, problem at the ground truth).
    """
    rng = np.random.default_rng(seed)
    poses, points, oc, op = _scene(n_cams, n_points, views, rng)
    K = np.tile([500.0, 500.0, 320.0, 240.0, 40.0], (n_cams, 1))
    st = rng.random(len(oc)) < stereo_fraction
    kern = kernel if kernel is not None else RobustKernel()
    zeros = np.zeros((len(oc), 3))
    true_proj = pinhole_residuals(poses, K, points, oc, op, zeros, np.ones(len(oc)))
    meas = true_proj + noise * rng.standard_normal(true_proj.shape)
    truth = PinholeProblem(poses, K, points, oc, op, meas, is_stereo=st,
                           information=np.full(len(oc), 1.0), kernel_mono=kern,
                           kernel_stereo=kern)  # fmt: skip
    xi = perturb * rng.standard_normal((n_cams, 6))
    init = truth.with_params(
        se3.retract(poses, xi), points + perturb * rng.standard_normal(points.shape)
    )
    return init, truth


def make_bal_problem(
    n_cams: int = 6,
    n_points: int = 40,
    views: int = 3,
    noise: float = 0.5,
    perturb: float = 0.02,
    seed: int = 0,
) -> tuple[BALProblem, BALProblem]:
    """A BAL problem (cameras look down -z, f = 500, small k1, k2) and its ground truth.

    Returns:
        (problem with the perturbed initial estimate, problem at the ground truth).
    """
    rng = np.random.default_rng(seed)
    poses, points, oc, op = _scene(n_cams, n_points, views, rng)
    return _bal(poses, points, oc, op, noise, perturb, rng)


def _bal(poses, points, oc, op, noise: float, perturb: float, rng: np.random.Generator):
    """BAL cameras from world-to-camera poses (M, 7), noisy pixels, perturbed start."""
    n_cams = len(poses)
    flip = np.diag([1.0, -1.0, -1.0])  # BAL cameras look down -z: rotate by pi about x
    cams = np.zeros((n_cams, 9))
    for i, T in enumerate(poses):
        R = flip @ so3.to_matrix(T[3:])
        cams[i, :3] = so3.log(so3.from_matrix(R))
        cams[i, 3:6] = flip @ T[:3]
    cams[:, 6] = 500.0
    cams[:, 7] = 1e-2
    cams[:, 8] = 1e-3
    pix = bal_residuals(cams, points, oc, op, np.zeros((len(oc), 2)))
    obs = pix + noise * rng.standard_normal(pix.shape)
    truth = BALProblem(cams, points, oc, op, obs)
    dc = perturb * rng.standard_normal((n_cams, 9)) * [1, 1, 1, 1, 1, 1, 100, 0, 0]
    init = truth.with_params(cams + dc, points + perturb * rng.standard_normal(points.shape))
    return init, truth


def _forward_scene(n_cams: int, n_points: int, mean_views: float, rng: np.random.Generator):
    """Forward-moving world-to-camera poses (M, 7), points (P, 3) and their runs of views."""
    ang = 0.02 * np.sin(np.arange(n_cams) / 15.0)  # a gentle yaw wobble
    poses = np.zeros((n_cams, 7))
    for i in range(n_cams):
        R_cw = so3.to_matrix(so3.exp(np.array([0.0, ang[i], 0.0]))).T
        poses[i] = np.r_[-R_cw @ np.array([0.0, 0.0, 1.0 * i]), so3.from_matrix(R_cw)]
    p = 1.0 / max(mean_views - 1.0, 1.0)
    length = np.clip(1 + rng.geometric(p, n_points), 2, min(12, n_cams))
    start = rng.integers(0, n_cams - length + 1)
    depth = rng.uniform(3.0, 30.0, n_points)  # from the run's last camera
    z = (start + length - 1) * 1.0 + depth
    x = rng.uniform(-0.6, 0.6, n_points) * depth
    y = rng.uniform(-0.3, 0.3, n_points) * depth
    op = np.repeat(np.arange(n_points), length)
    oc = np.repeat(start, length) + (
        np.arange(len(op)) - np.repeat(np.cumsum(length) - length, length)
    )
    return poses, np.stack([x, y, z], 1), oc.astype(np.int64), op.astype(np.int64)


def make_forward_problem(
    n_cams: int = 20,
    n_points: int = 400,
    mean_views: float = 3.6,
    model: str = "bal",
    noise: float = 0.5,
    perturb: float = 0.01,
    seed: int = 0,
) -> tuple[BALProblem | PinholeProblem, BALProblem | PinholeProblem]:
    """A visual-odometry-shaped problem and its ground truth: the camera moves 1 m per view
    along its optical axis (with a small yaw wobble) and each point is seen by a run of
    ``L = clip(1 + Geometric(1 / (mean_views - 1)), 2, 12)`` consecutive views.

    KITTI-07 size: ``(248, 26127, 3.64)``; KITTI-00 size: ``(1332, 133383, 4.21)``.

    Args:
        n_cams, n_points: M and P.
        mean_views: mean run length before the clip (the clip lowers it slightly).
        model: "bal" (BALProblem, 9-parameter cameras) or "pinhole" (PinholeProblem, monocular
            edges, fx = fy = 500, no robust kernel).
        noise: pixel noise (std).
        perturb: scale of the perturbation of the initial estimate.
        seed: RNG seed.

    Returns:
        (problem with the perturbed initial estimate, problem at the ground truth).
    """
    if model not in ("bal", "pinhole"):
        raise ValueError(f"model: expected 'bal' or 'pinhole', got {model!r}")
    if n_cams < 2:
        raise ValueError(f"n_cams: must be >= 2, got {n_cams}")
    rng = np.random.default_rng(seed)
    poses, points, oc, op = _forward_scene(n_cams, n_points, mean_views, rng)
    if model == "bal":  # perturb centres and rotations, not BAL's t = -R c (lever arm)
        truth, _ = _bal(poses, points, oc, op, noise, 0.0, rng)
        c = -np.einsum("mji,mj->mi", so3.to_matrix(poses[:, 3:]), poses[:, :3])
        R = so3.to_matrix(poses[:, 3:]) @ so3.to_matrix(
            so3.exp(perturb * rng.standard_normal((n_cams, 3)))
        )
        c = c + perturb * rng.standard_normal(c.shape)
        q = so3.from_matrix(R)
        moved = np.concatenate([-np.einsum("mij,mj->mi", R, c), q], 1)
        start, _ = _bal(moved, points, oc, op, 0.0, 0.0, rng)
        pts = points + perturb * rng.standard_normal(points.shape)
        return truth.with_params(start.cameras, pts), truth
    K = np.tile([500.0, 500.0, 320.0, 240.0, 40.0], (n_cams, 1))
    zeros = np.zeros((len(oc), 3))
    proj = pinhole_residuals(poses, K, points, oc, op, zeros, np.zeros(len(oc)))
    meas = proj + noise * rng.standard_normal(proj.shape)
    meas[:, 2] = 0.0
    truth = PinholeProblem(poses, K, points, oc, op, meas, is_stereo=np.zeros(len(oc), bool),
                           information=np.ones(len(oc)), pose_fixed=np.arange(n_cams) == 0)  # fmt: skip
    init = truth.with_params(
        se3.retract(poses, perturb * rng.standard_normal((n_cams, 6))),
        points + perturb * rng.standard_normal(points.shape),
    )
    return init, truth
