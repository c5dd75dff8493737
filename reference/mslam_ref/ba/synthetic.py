"""Bundle adjustment — small synthetic problems for tests, tutorials and parity checks.

Cameras on a ring look at a cloud of points; every point is seen by several cameras; the
measurements are exact projections plus Gaussian pixel noise, and the initial estimate is the
truth perturbed. Deterministic for a given ``seed``.

Public functions: make_pinhole_problem, make_bal_problem.
"""

from __future__ import annotations

import numpy as np

from mslam_ref import se3, so3
from mslam_ref.ba.cameras import bal_residuals, pinhole_residuals
from mslam_ref.ba.problem import BALProblem, PinholeProblem
from mslam_ref.ba.robust import RobustKernel

__all__ = ["make_bal_problem", "make_pinhole_problem"]


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
