"""Taichi twin of ``mslam_ref.ba.cameras`` — same names, parameters and shapes; see there for the maths.

Each public function runs one parallel loop over the O observations (one observation per
iteration, no reductions); projection, residual and both Jacobians are fused in one pass. The
BAL functions first compute each camera's rotation matrix (M items), so the observations' loop
has no sin/cos. Inputs are coerced to the runtime dtype; indices stay int64. The residual and
Jacobian arrays are recycled once the caller has released them (``mslam_fast._recycle``).
"""

from typing import Any

import numpy as np
import taichi as ti

from mslam_fast._kernels import ba as K
from mslam_fast._recycle import output
from mslam_fast._runtime import ensure_init, prepare
from mslam_fast._types import nd, template

__all__ = [
    "bal_linearize",
    "bal_residuals",
    "pinhole_linearize",
    "pinhole_residuals",
]

Array = np.ndarray[Any, Any]


@ti.func
def _load(A: template, i, n: template):
    return ti.Vector([A[i, k] for k in ti.static(range(n))])


@ti.kernel
def _bal_rot_k(cams: nd, R: nd):
    for c in range(cams.shape[0]):  # one rotation per camera, shared by its observations
        Rc = K.rodrigues(ti.Vector([cams[c, 0], cams[c, 1], cams[c, 2]]))
        for i in ti.static(range(3)):
            for j in ti.static(range(3)):
                R[c, i, j] = Rc[i, j]


@ti.func
def _rot(R: template, c):
    return ti.Matrix([[R[c, i, j] for j in ti.static(range(3))] for i in ti.static(range(3))])


@ti.kernel
def _bal_res_k(cams: nd, R: nd, pts: nd, oc: nd, op: nd, obs: nd, r: nd):
    for e in range(oc.shape[0]):
        c = oc[e]
        pix, _R, _RX, _P, _p, _r2, _d = K.bal_project(
            _load(cams, c, 9), _rot(R, c), _load(pts, op[e], 3)
        )
        for i in ti.static(range(2)):
            r[e, i] = pix[i] - obs[e, i]


@ti.kernel
def _bal_lin_k(cams: nd, Rc: nd, pts: nd, oc: nd, op: nd, obs: nd, r: nd, Jc: nd, Jp: nd):
    for e in range(oc.shape[0]):
        c = oc[e]
        cam = _load(cams, c, 9)
        pix, R, RX, P, p, r2, d = K.bal_project(cam, _rot(Rc, c), _load(pts, op[e], 3))
        A, B = K.bal_jacobians(cam, R, RX, P, p, r2, d)
        for i in ti.static(range(2)):
            r[e, i] = pix[i] - obs[e, i]
            for j in ti.static(range(9)):
                Jc[e, i, j] = A[i, j]
            for j in ti.static(range(3)):
                Jp[e, i, j] = B[i, j]


@ti.kernel
def _pin_res_k(poses: nd, intr: nd, pts: nd, oc: nd, op: nd, meas: nd, st: nd, r: nd):
    for e in range(oc.shape[0]):
        proj, _Xc, _R = K.pinhole_project(
            _load(poses, oc[e], 7), _load(intr, oc[e], 5), _load(pts, op[e], 3)
        )
        for i in ti.static(range(2)):
            r[e, i] = proj[i] - meas[e, i]
        r[e, 2] = (proj[2] - meas[e, 2]) * st[e]


@ti.kernel
def _pin_lin_k(
    poses: nd, intr: nd, pts: nd, oc: nd, op: nd, meas: nd, st: nd, r: nd, Jc: nd, Jp: nd
):
    for e in range(oc.shape[0]):
        Kc = _load(intr, oc[e], 5)
        proj, Xc, R = K.pinhole_project(_load(poses, oc[e], 7), Kc, _load(pts, op[e], 3))
        A, B = K.pinhole_jacobians(Kc, Xc, R, st[e])
        for i in ti.static(range(2)):
            r[e, i] = proj[i] - meas[e, i]
        r[e, 2] = (proj[2] - meas[e, 2]) * st[e]
        for i in ti.static(range(3)):
            for j in ti.static(range(6)):
                Jc[e, i, j] = A[i, j]
            for j in ti.static(range(3)):
                Jp[e, i, j] = B[i, j]


def _idx(x: Any) -> Array:
    return np.ascontiguousarray(x, dtype=np.int64)


def _empty(*shape: int) -> Array:
    return np.zeros(shape, dtype=ensure_init().dtype)


def _out(key: str, *shape: int) -> Array:
    """A recycled output (``mslam_fast._recycle``): the kernels write every element."""
    return output(key, shape, ensure_init().dtype)


def _bal_args(cameras: Any, points: Any, obs_cam: Any, obs_pt: Any, obs: Any) -> tuple:
    """Coerced inputs with the (M, 3, 3) camera rotations in second place."""
    cams = prepare(cameras, "cameras", 9)
    R = _empty(len(cams), 3, 3)
    if len(cams):
        _bal_rot_k(cams, R)
    return (cams, R, prepare(points, "points", 3), _idx(obs_cam), _idx(obs_pt),
            prepare(obs, "obs", 2))  # fmt: skip


def bal_residuals(cameras: Any, points: Any, obs_cam: Any, obs_pt: Any, obs: Any) -> Array:
    """Taichi twin of ``mslam_ref.ba.cameras.bal_residuals`` (rotations per camera, then
    parallel over O)."""
    args = _bal_args(cameras, points, obs_cam, obs_pt, obs)
    r = _out("bal_r", len(args[3]), 2)
    if len(r):
        _bal_res_k(*args, r)
    return r


def bal_linearize(
    cameras: Any, points: Any, obs_cam: Any, obs_pt: Any, obs: Any
) -> tuple[Array, Array, Array]:
    """Taichi twin of ``mslam_ref.ba.cameras.bal_linearize`` (rotations per camera, then
    parallel over O, fused)."""
    args = _bal_args(cameras, points, obs_cam, obs_pt, obs)
    O = len(args[3])
    r, Jc, Jp = _out("bal_lin_r", O, 2), _out("bal_Jc", O, 2, 9), _out("bal_Jp", O, 2, 3)
    if O:
        _bal_lin_k(*args, r, Jc, Jp)
    return r, Jc, Jp


def _pin_args(poses, intrinsics, points, obs_cam, obs_pt, meas, is_stereo):
    return (prepare(poses, "poses", 7), prepare(intrinsics, "intrinsics", 5),
            prepare(points, "points", 3), _idx(obs_cam), _idx(obs_pt), prepare(meas, "meas", 3),
            prepare(is_stereo, "is_stereo", None))  # fmt: skip


def pinhole_residuals(poses, intrinsics, points, obs_cam, obs_pt, meas, is_stereo) -> Array:
    """Taichi twin of ``mslam_ref.ba.cameras.pinhole_residuals`` (parallel over O)."""
    args = _pin_args(poses, intrinsics, points, obs_cam, obs_pt, meas, is_stereo)
    r = _out("pin_r", len(args[3]), 3)
    if len(r):
        _pin_res_k(*args, r)
    return r


def pinhole_linearize(
    poses, intrinsics, points, obs_cam, obs_pt, meas, is_stereo
) -> tuple[Array, Array, Array]:
    """Taichi twin of ``mslam_ref.ba.cameras.pinhole_linearize`` (parallel over O, fused)."""
    args = _pin_args(poses, intrinsics, points, obs_cam, obs_pt, meas, is_stereo)
    O = len(args[3])
    r, Jc, Jp = _out("pin_lin_r", O, 3), _out("pin_Jc", O, 3, 6), _out("pin_Jp", O, 3, 3)
    if O:
        _pin_lin_k(*args, r, Jc, Jp)
    return r, Jc, Jp
