"""Bundle adjustment — the problem model: cameras, points, observations, fixed flags, kernels.

Two problem types share one interface, which the LM driver (``mslam_ref.ba.lm``) uses:

* :class:`PinholeProblem` — cuda-bundle-adjustment / g2o ``BlockSolver_6_3``: SE(3) pose
  vertices ``[t, q_xyzw]`` (world to camera, 6-DoF left increments) each with its own
  ``(fx, fy, cx, cy, bf)``, landmark vertices ``Xw``, mono edges ``(u, v)`` and stereo edges
  ``(u, v, ur)``, one scalar information per edge, one robust kernel per edge type;
* :class:`BALProblem` — BAL cameras ``[w, t, f, k1, k2]`` (9-DoF blocks) and points.

The interface: ``cam_dof`` (d), ``params() -> (cams, points)``, ``with_params(cams, points)``,
``residuals(kernels, cams, points) -> r (O, k)``, ``linearize(kernels, cams, points) -> (r,
J_cam (O, k, d), J_pt (O, k, 3))`` (Jacobian rows of fixed vertices zeroed),
``retract(cams, points, dc, dl)``, ``robust(s) -> (rho, weight)``, ``information`` (O,),
``cam_free`` (M,), ``point_free`` (P,) and ``edge_active`` (O,) (an edge between two fixed
vertices is dropped, as cuda-bundle-adjustment does). ``kernels`` is a kernel-set namespace
(``mslam_ref.ba`` or ``mslam_fast.ba``) whose ``cameras`` module computes the residuals.

Shapes: M cameras, P points, O observations.

Upstream: cuda-bundle-adjustment include/cuda_bundle_adjustment_types.h (PoseVertex,
LandmarkVertex, MonoEdge, StereoEdge, CameraParams); Ceres examples/bal_problem.h.
"""

from __future__ import annotations

import dataclasses
from typing import Any, cast

import numpy as np

from mslam_ref import se3
from mslam_ref.ba.cameras import bal_retract_cameras
from mslam_ref.ba.robust import RobustKernel, rho_and_weight
from mslam_ref.conventions import BoolArray, FloatArray, IntArray, as_float_array

__all__ = ["BALProblem", "PinholeProblem"]

#: The default kernel (plain least squares).
_NO_KERNEL = RobustKernel()


def _index(x: Any, name: str, n: int, O: int | None = None) -> IntArray:
    arr = np.asarray(x)
    if arr.ndim != 1 or (O is not None and arr.shape[0] != O):
        raise ValueError(
            f"{name}: expected shape ({O if O is not None else 'O'},), got {arr.shape}"
        )
    if arr.size and (not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 or arr.max() >= n):
        raise ValueError(f"{name}: indices must be integers in [0, {n})")
    return arr.astype(np.int64)


def _mask(x: Any, name: str, n: int) -> BoolArray:
    if x is None:
        return np.zeros(n, bool)
    arr = np.asarray(x, dtype=bool)
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {arr.shape}")
    return arr


def _set(obj: Any, **kw: Any) -> None:
    for k, v in kw.items():
        object.__setattr__(obj, k, v)


class _Common:
    """Shared helpers of both problem types (masks of unknowns and active edges)."""

    obs_cam: IntArray
    obs_pt: IntArray
    # Set by _derive_masks in the subclasses' __post_init__.
    edge_active: BoolArray
    cam_free: BoolArray
    point_free: BoolArray

    def _derive_masks(self, cam_fixed: BoolArray, point_fixed: BoolArray) -> None:
        M, P = len(cam_fixed), len(point_fixed)
        active = ~(cam_fixed[self.obs_cam] & point_fixed[self.obs_pt])
        seen_c = np.bincount(self.obs_cam[active], minlength=M) > 0
        seen_p = np.bincount(self.obs_pt[active], minlength=P) > 0
        _set(
            self, edge_active=active, cam_free=~cam_fixed & seen_c, point_free=~point_fixed & seen_p
        )

    def _mask_jacobians(self, r: FloatArray, Jc: FloatArray, Jp: FloatArray):
        cam_off = ~self.cam_free[self.obs_cam]
        pt_off = ~self.point_free[self.obs_pt]
        if cam_off.any():
            Jc[cam_off] = 0.0
        if pt_off.any():
            Jp[pt_off] = 0.0
        inactive = ~self.edge_active
        if inactive.any():
            r[inactive] = 0.0
        return r, Jc, Jp


@dataclasses.dataclass(frozen=True, eq=False)
class BALProblem(_Common):
    """A BAL problem: cameras (M, 9) ``[w, t, f, k1, k2]``, points (P, 3), observations.

    Attributes:
        cameras: (M, 9).
        points: (P, 3).
        obs_cam: (O,) camera index per observation.
        obs_pt: (O,) point index per observation.
        obs: (O, 2) observed pixels (image-centred, y up).
        kernel: robust kernel applied to ``s = |r|^2`` (default none, as the BAL benchmarks).
        cam_fixed: (M,) bool, optional.
        point_fixed: (P,) bool, optional.
    """

    cameras: FloatArray
    points: FloatArray
    obs_cam: IntArray
    obs_pt: IntArray
    obs: FloatArray
    kernel: RobustKernel = _NO_KERNEL
    cam_fixed: BoolArray | None = None
    point_fixed: BoolArray | None = None

    cam_dof = 9
    res_dim = 2

    def __post_init__(self) -> None:
        cams = as_float_array(self.cameras, "cameras", 9).reshape(-1, 9)
        pts = as_float_array(self.points, "points", 3).reshape(-1, 3)
        oc = _index(self.obs_cam, "obs_cam", len(cams))
        op = _index(self.obs_pt, "obs_pt", len(pts), len(oc))
        obs = as_float_array(self.obs, "obs", 2)
        if obs.shape != (len(oc), 2):
            raise ValueError(f"obs: expected shape ({len(oc)}, 2), got {obs.shape}")
        cf = _mask(self.cam_fixed, "cam_fixed", len(cams))
        pf = _mask(self.point_fixed, "point_fixed", len(pts))
        _set(
            self,
            cameras=cams,
            points=pts,
            obs_cam=oc,
            obs_pt=op,
            obs=obs,
            cam_fixed=cf,
            point_fixed=pf,
            information=np.ones(len(oc)),
        )
        self._derive_masks(cf, pf)

    def params(self) -> tuple[FloatArray, FloatArray]:
        """The optimised parameters ``(cameras (M, 9), points (P, 3))``."""
        return self.cameras, self.points

    def with_params(self, cams: FloatArray, points: FloatArray) -> BALProblem:
        """A copy of the problem with new parameters."""
        return dataclasses.replace(self, cameras=cams, points=points)

    def robust(self, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``rho(s)`` and ``rho'(s)`` per edge."""
        return rho_and_weight(s, self.kernel)

    def residuals(self, kernels: Any, cams: FloatArray, points: FloatArray) -> FloatArray:
        """(O, 2) residuals (zero for inactive edges)."""
        r = kernels.cameras.bal_residuals(cams, points, self.obs_cam, self.obs_pt, self.obs)
        r[~self.edge_active] = 0.0
        return r

    def linearize(self, kernels: Any, cams: FloatArray, points: FloatArray):
        """r (O, 2), J_cam (O, 2, 9), J_pt (O, 2, 3) with fixed blocks zeroed."""
        out = kernels.cameras.bal_linearize(cams, points, self.obs_cam, self.obs_pt, self.obs)
        return self._mask_jacobians(*out)

    def retract(self, cams: FloatArray, points: FloatArray, dc: FloatArray, dl: FloatArray):
        """Apply the increments (M, 9) and (P, 3)."""
        return bal_retract_cameras(cams, dc), points + dl


@dataclasses.dataclass(frozen=True, eq=False)
class PinholeProblem(_Common):
    """A g2o/cuda-bundle-adjustment problem with SE(3) poses and mono/stereo edges.

    Attributes:
        poses: (M, 7) ``[t, q_xyzw]`` world to camera.
        intrinsics: (M, 5) ``(fx, fy, cx, cy, bf)`` per pose.
        points: (P, 3) world points.
        obs_cam: (O,) pose index per edge.
        obs_pt: (O,) landmark index per edge.
        meas: (O, 3) ``(u, v, ur)`` (``ur`` unused for mono edges) or (O, 2) for all-mono.
        is_stereo: (O,) bool, optional (default all mono).
        information: (O,) scalar information ``omega`` per edge, optional (default 1).
        pose_fixed: (M,) bool, optional.
        point_fixed: (P,) bool, optional.
        kernel_mono: robust kernel of the mono edges.
        kernel_stereo: robust kernel of the stereo edges.
    """

    poses: FloatArray
    intrinsics: FloatArray
    points: FloatArray
    obs_cam: IntArray
    obs_pt: IntArray
    meas: FloatArray
    is_stereo: BoolArray | None = None
    information: FloatArray | None = None
    pose_fixed: BoolArray | None = None
    point_fixed: BoolArray | None = None
    kernel_mono: RobustKernel = _NO_KERNEL
    kernel_stereo: RobustKernel = _NO_KERNEL

    cam_dof = 6
    res_dim = 3

    def __post_init__(self) -> None:
        poses = se3.validate(np.asarray(self.poses, dtype=np.float64).reshape(-1, 7), "poses")
        K = as_float_array(self.intrinsics, "intrinsics", 5).reshape(-1, 5)
        if K.shape[0] != poses.shape[0]:
            raise ValueError(f"intrinsics: expected {poses.shape[0]} rows, got {K.shape[0]}")
        pts = as_float_array(self.points, "points", 3).reshape(-1, 3)
        oc = _index(self.obs_cam, "obs_cam", len(poses))
        op = _index(self.obs_pt, "obs_pt", len(pts), len(oc))
        meas = as_float_array(self.meas, "meas")
        if meas.shape == (len(oc), 2):
            meas = np.concatenate([meas, np.zeros((len(oc), 1))], axis=1)
        if meas.shape != (len(oc), 3):
            raise ValueError(f"meas: expected shape ({len(oc)}, 3), got {meas.shape}")
        st = _mask(self.is_stereo, "is_stereo", len(oc))
        info = (
            np.ones(len(oc))
            if self.information is None
            else as_float_array(self.information, "information")
        )
        if info.shape != (len(oc),) or np.any(info <= 0.0):
            raise ValueError("information: expected (O,) positive values")
        pf = _mask(self.pose_fixed, "pose_fixed", len(poses))
        lf = _mask(self.point_fixed, "point_fixed", len(pts))
        _set(
            self,
            poses=poses,
            intrinsics=K,
            points=pts,
            obs_cam=oc,
            obs_pt=op,
            meas=meas,
            is_stereo=st,
            information=info,
            pose_fixed=pf,
            point_fixed=lf,
        )
        self._derive_masks(pf, lf)

    def params(self) -> tuple[FloatArray, FloatArray]:
        """The optimised parameters ``(poses (M, 7), points (P, 3))``."""
        return self.poses, self.points

    def with_params(self, cams: FloatArray, points: FloatArray) -> PinholeProblem:
        """A copy of the problem with new parameters."""
        return dataclasses.replace(self, poses=cams, points=points)

    def robust(self, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``rho(s)`` and ``rho'(s)`` per edge, with the mono or stereo kernel."""
        st = cast(BoolArray, self.is_stereo)  # (O,) after __post_init__
        rho_m, w_m = rho_and_weight(s, self.kernel_mono)
        if not st.any():
            return rho_m, w_m
        rho_s, w_s = rho_and_weight(s, self.kernel_stereo)
        return np.where(st, rho_s, rho_m), np.where(st, w_s, w_m)

    def _args(self, cams: FloatArray, points: FloatArray) -> tuple[Any, ...]:
        return (
            cams,
            self.intrinsics,
            points,
            self.obs_cam,
            self.obs_pt,
            self.meas,
            cast(BoolArray, self.is_stereo).astype(np.float64),
        )

    def residuals(self, kernels: Any, cams: FloatArray, points: FloatArray) -> FloatArray:
        """(O, 3) residuals (zero for inactive edges)."""
        r = kernels.cameras.pinhole_residuals(*self._args(cams, points))
        r[~self.edge_active] = 0.0
        return r

    def linearize(self, kernels: Any, cams: FloatArray, points: FloatArray):
        """r (O, 3), J_cam (O, 3, 6), J_pt (O, 3, 3) with fixed blocks zeroed."""
        return self._mask_jacobians(*kernels.cameras.pinhole_linearize(*self._args(cams, points)))

    def retract(self, cams: FloatArray, points: FloatArray, dc: FloatArray, dl: FloatArray):
        """Apply ``T <- exp(xi) T`` (M, 6) and ``X <- X + dl`` (P, 3)."""
        return se3.retract(cams, dc), points + dl
