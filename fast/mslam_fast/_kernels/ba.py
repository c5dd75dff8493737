"""``@ti.func`` building blocks of the bundle adjuster; the maths is in ``mslam_ref.ba.cameras``.

Every func takes and returns Taichi vectors/matrices in the runtime's ``default_fp``; sums that
run over observations are accumulated by the callers in ``ti.f64`` locals.
"""

import taichi as ti

from mslam_fast._kernels.sim3 import quat_to_matrix

EPS_ROT = 1e-5  # small-angle switch of the Rodrigues coefficients (g2o / cuda-ba)


@ti.func
def hat(v):
    """Skew-symmetric matrix [v]x."""
    return ti.Matrix([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@ti.func
def rodrigues(w):
    """R = I + a1 [w]x + a2 [w]x^2 with a1 = sin t/t, a2 = (1 - cos t)/t^2 (Taylor 1, 1/2)."""
    th = w.norm()
    a1 = 1.0
    a2 = 0.5
    if th >= EPS_ROT:
        a1 = ti.sin(th) / th
        a2 = (1.0 - ti.cos(th)) / (th * th)
    W = hat(w)
    return ti.Matrix.identity(float, 3) + a1 * W + a2 * (W @ W)


@ti.func
def bal_project(cam, R, X):
    """BAL model: P = R X + t, p = -P_xy / P_z, pixel = f (1 + k1 |p|^2 + k2 |p|^4) p, with
    the camera's rotation ``R = rodrigues(cam[:3])`` given (computed once per camera).

    Returns (pixel (2,), R (3x3), RX (3,), P (3,), p (2,), r2, d).
    """
    RX = R @ X
    P = RX + ti.Vector([cam[3], cam[4], cam[5]])
    p = ti.Vector([-P[0] / P[2], -P[1] / P[2]])
    r2 = p.dot(p)
    d = 1.0 + cam[7] * r2 + cam[8] * r2 * r2
    return cam[6] * d * p, R, RX, P, p, r2, d


@ti.func
def bal_jacobians(cam, R, RX, P, p, r2, d):
    """dpixel/d[delta_rot, t, f, k1, k2] (2x9) and dpixel/dX (2x3)."""
    f = cam[6]
    c = 2.0 * f * (cam[7] + 2.0 * cam[8] * r2)
    Dp = ti.Matrix(
        [[f * d + c * p[0] * p[0], c * p[0] * p[1]], [c * p[1] * p[0], f * d + c * p[1] * p[1]]]
    )
    iz = 1.0 / P[2]
    dpdP = ti.Matrix([[-iz, 0.0, P[0] * iz * iz], [0.0, -iz, P[1] * iz * iz]])
    A = Dp @ dpdP
    Jr = A @ (-hat(RX))
    Jc = ti.Matrix.zero(float, 2, 9)
    for i in ti.static(range(2)):
        for j in ti.static(range(3)):
            Jc[i, j] = Jr[i, j]
            Jc[i, 3 + j] = A[i, j]
        Jc[i, 6] = d * p[i]
        Jc[i, 7] = f * r2 * p[i]
        Jc[i, 8] = f * r2 * r2 * p[i]
    return Jc, A @ R


@ti.func
def pinhole_project(T, K, X):
    """Xc = R X + t; (u, v, ur) = (fx X/Z + cx, fy Y/Z + cy, u - bf/Z). Returns (proj, Xc, R)."""
    R = quat_to_matrix(ti.Vector([T[3], T[4], T[5], T[6]]))
    Xc = R @ X + ti.Vector([T[0], T[1], T[2]])
    iz = 1.0 / Xc[2]
    u = K[0] * Xc[0] * iz + K[2]
    v = K[1] * Xc[1] * iz + K[3]
    return ti.Vector([u, v, u - K[4] * iz]), Xc, R


@ti.func
def pinhole_jacobians(K, Xc, R, stereo):
    """dproj/d[omega, upsilon] (3x6) and dproj/dX (3x3); third rows zero unless ``stereo``."""
    iz = 1.0 / Xc[2]
    D = ti.Matrix(
        [
            [K[0] * iz, 0.0, -K[0] * Xc[0] * iz * iz],
            [0.0, K[1] * iz, -K[1] * Xc[1] * iz * iz],
            [K[0] * iz, 0.0, -K[0] * Xc[0] * iz * iz + K[4] * iz * iz],
        ]
    )
    for j in ti.static(range(3)):
        D[2, j] *= stereo
    dX = ti.Matrix.zero(float, 3, 6)
    H = -hat(Xc)
    for i in ti.static(range(3)):
        for j in ti.static(range(3)):
            dX[i, j] = H[i, j]
        dX[i, 3 + i] = 1.0
    return D @ dX, D @ R


@ti.func
def inv3(A):
    """Inverse of a 3x3 matrix by the adjugate over the determinant (inf when det == 0)."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    adj = ti.Matrix(
        [
            [c00, A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2], A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]],
            [c01, A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0], A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]],
            [c02, A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1], A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]],
        ]
    )
    return adj / det
