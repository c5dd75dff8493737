"""``@ti.func`` building blocks for SO(3) and Sim(3); the maths is in ``mslam_ref.sim3``/``so3``.

Conventions inside Taichi scope: a Sim(3) element is an 8-vector ``[t, q_xyzw, s]``, a tangent a
7-vector ``[tau, phi, sigma]``, a quaternion a 4-vector ``[qx, qy, qz, qw]``. Scalars follow the
runtime's ``default_fp``. Other kernels (matching, tracking, backend, BA) import these funcs.
"""

import taichi as ti

from mslam_fast._types import template

EPS = 1e-6  # series threshold of Exp/Log, as lietorch


@ti.func
def load(A: template, i, n: template):
    """Row ``i`` of a 2-D ndarray ``A`` as an ``n``-vector."""
    return ti.Vector([A[i, k] for k in ti.static(range(n))])


@ti.func
def store(A: template, i, v: template):
    """Write the vector ``v`` into row ``i`` of a 2-D ndarray ``A``."""
    for k in ti.static(range(v.n)):
        A[i, k] = v[k]


@ti.func
def store_mat(A: template, i, M: template):
    """Write the matrix ``M`` into slice ``i`` of a 3-D ndarray ``A``."""
    for r in ti.static(range(M.n)):
        for c in ti.static(range(M.m)):
            A[i, r, c] = M[r, c]


@ti.func
def hat(v):
    """Skew-symmetric matrix [v]x."""
    return ti.Matrix([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@ti.func
def trans(T):
    return ti.Vector([T[0], T[1], T[2]])


@ti.func
def quat(T):
    return ti.Vector([T[3], T[4], T[5], T[6]])


@ti.func
def pack(t, q, s):
    """Assemble ``[t, q, s]`` into an 8-vector."""
    return ti.Vector([t[0], t[1], t[2], q[0], q[1], q[2], q[3], s])


@ti.func
def quat_normalize(q):
    return q / q.norm()


@ti.func
def quat_mul(q1, q2):
    """Hamilton product q1 ⊗ q2."""
    v1 = ti.Vector([q1[0], q1[1], q1[2]])
    v2 = ti.Vector([q2[0], q2[1], q2[2]])
    v = q1[3] * v2 + q2[3] * v1 + v1.cross(v2)
    return ti.Vector([v[0], v[1], v[2], q1[3] * q2[3] - v1.dot(v2)])


@ti.func
def quat_conj(q):
    return ti.Vector([-q[0], -q[1], -q[2], q[3]])


@ti.func
def quat_act(q, X):
    """R(q) X with u = 2 q_v x X, Y = X + w u + q_v x u (gn_kernels.cu::actSO3)."""
    qv = ti.Vector([q[0], q[1], q[2]])
    u = 2.0 * qv.cross(X)
    return X + q[3] * u + qv.cross(u)


@ti.func
def quat_to_matrix(q):
    x, y, z, w = q[0], q[1], q[2], q[3]
    return ti.Matrix(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@ti.func
def so3_exp(phi):
    th2 = phi.dot(phi)
    th = ti.sqrt(th2)
    imag = 0.0
    real = 0.0
    if th < EPS:
        imag = 0.5 - th2 / 48.0 + th2 * th2 / 3840.0
        real = 1.0 - th2 / 8.0 + th2 * th2 / 384.0
    else:
        imag = ti.sin(0.5 * th) / th
        real = ti.cos(0.5 * th)
    return ti.Vector([imag * phi[0], imag * phi[1], imag * phi[2], real])


@ti.func
def so3_log(q):
    qv = ti.Vector([q[0], q[1], q[2]])
    w = q[3]
    n2 = qv.dot(qv)
    n = ti.sqrt(n2)
    f = 0.0
    if n2 < EPS * EPS:
        f = 2.0 / w - (2.0 / 3.0) * n2 / (w * w * w)
    else:  # exact up to w = 0 (lietorch's +-pi/n for |w| < EPS errs by up to 2|w|)
        f = (2.0 if w >= 0.0 else -2.0) * ti.atan2(n, ti.abs(w)) / n
    return f * qv


@ti.func
def W_coefficients(th_, sigma_):
    """A, B, C of W = A Phi + B Phi^2 + C I (see mslam_ref.sim3._W_coefficients).

    Evaluated in f64 whatever the runtime precision, then cast back to ``default_fp``: in f32
    the closed forms cancel catastrophically (e.g. ``((sigma - 1) s + 1) / sigma^2`` at
    sigma ~ 1e-6, or ``(1 - cos th) / th^2`` at th ~ 1e-4), which gave errors up to 1e-2 in t.
    """
    th = ti.cast(th_, ti.f64)
    sigma = ti.cast(sigma_, ti.f64)
    A = ti.f64(0.0)
    B = ti.f64(0.0)
    C = ti.f64(0.0)
    if ti.abs(sigma) < EPS:
        C = 1.0 + sigma / 2.0 + sigma * sigma / 6.0
        if th < EPS:
            A = 0.5 + sigma / 3.0
            B = 1.0 / 6.0
        else:
            c, s_ = ti.cos(th), ti.sin(th)
            sh = ti.sin(0.5 * th)  # 1 - cos th = 2 sin^2(th/2), no cancellation
            A = 2.0 * sh * sh / (th * th) + sigma * (s_ - th * c) / (th * th * th)
            B = (th - s_) / (th * th * th) + sigma * (
                0.5 / (th * th) - (c + th * s_ - 1.0) / (th * th * th * th)
            )
    else:
        s = ti.exp(sigma)
        C = (s - 1.0) / ti.log(s)  # = expm1(sigma)/sigma (Kahan); (s - 1)/sigma loses 1e-10
        if th < EPS and ti.abs(sigma) < 1e-2:  # series: the closed forms cancel
            sg = sigma
            A = 0.5 + sg / 3.0 + sg * sg / 8.0 + sg * sg * sg / 30.0 + sg * sg * sg * sg / 144.0
            B = 1.0 / 6.0 + sg / 8.0 + sg * sg / 20.0 + sg * sg * sg / 72.0
            B += sg * sg * sg * sg / 336.0
        elif th < EPS:
            A = ((sigma - 1.0) * s + 1.0) / (sigma * sigma)
            B = (s * sigma * sigma / 2.0 + s - 1.0 - sigma * s) / (sigma * sigma * sigma)
        else:
            a = s * ti.sin(th)
            b = s * ti.cos(th)
            cc = th * th + sigma * sigma
            A = (a * sigma + (1.0 - b) * th) / (th * cc)
            B = (C - ((b - 1.0) * sigma + a * th) / cc) / (th * th)
    return ti.cast(A, float), ti.cast(B, float), ti.cast(C, float)


@ti.func
def sim3_exp(xi):
    tau = ti.Vector([xi[0], xi[1], xi[2]])
    phi = ti.Vector([xi[3], xi[4], xi[5]])
    sigma = xi[6]
    A, B, C = W_coefficients(phi.norm(), sigma)
    Phi = hat(phi)
    t = A * (Phi @ tau) + B * (Phi @ (Phi @ tau)) + C * tau
    return pack(t, so3_exp(phi), ti.exp(sigma))


@ti.func
def sim3_log(T):
    q = quat(T)
    phi = so3_log(q)
    sigma = ti.log(T[7])
    A, B, C = W_coefficients(phi.norm(), sigma)
    Phi = hat(phi)
    # W / C has entries O(1) for every sigma: the cofactor inverse of W itself overflows its
    # determinant (~ C^3) for sigma >~ 240, where C ~ e^sigma / sigma.
    W = (A / C) * Phi + (B / C) * (Phi @ Phi)
    for k in ti.static(range(3)):
        W[k, k] += 1.0
    tau = W.inverse() @ (trans(T) / C)
    return ti.Vector([tau[0], tau[1], tau[2], phi[0], phi[1], phi[2], sigma])


@ti.func
def sim3_mul(A, B):
    qA = quat(A)
    t = trans(A) + A[7] * quat_act(qA, trans(B))
    return pack(t, quat_mul(qA, quat(B)), A[7] * B[7])


@ti.func
def sim3_inv(T):
    qi = quat_conj(quat(T))
    t = -quat_act(qi, trans(T)) / T[7]
    return pack(t, qi, 1.0 / T[7])


@ti.func
def sim3_act(T, X):
    """s R X + t."""
    return T[7] * quat_act(quat(T), X) + trans(T)


@ti.func
def sim3_act_jacobian(P):
    """dP/dxi = [I | -[P]x | P] (3x7) at the transformed point P."""
    return ti.Matrix(
        [
            [1.0, 0.0, 0.0, 0.0, P[2], -P[1], P[0]],
            [0.0, 1.0, 0.0, -P[2], 0.0, P[0], P[1]],
            [0.0, 0.0, 1.0, P[1], -P[0], 0.0, P[2]],
        ]
    )


@ti.func
def sim3_adjoint(T):
    t = trans(T)
    R = quat_to_matrix(quat(T))
    tR = hat(t) @ R
    Ad = ti.Matrix.zero(float, 7, 7)
    for r in ti.static(range(3)):
        for c in ti.static(range(3)):
            Ad[r, c] = T[7] * R[r, c]
            Ad[r, c + 3] = tR[r, c]
            Ad[r + 3, c + 3] = R[r, c]
        Ad[r, 6] = -t[r]
    Ad[6, 6] = 1.0
    return Ad


@ti.func
def sim3_adj_inv_apply(T, J):
    """Row J times Ad(T)^-1 (gn_kernels.cu::apply_Sim3_adj_inv)."""
    q = quat(T)
    t = trans(T)
    inv_s = 1.0 / T[7]
    Ra = quat_act(q, ti.Vector([J[0], J[1], J[2]]))
    y_tau = Ra * inv_s
    y_phi = quat_act(q, ti.Vector([J[3], J[4], J[5]])) + t.cross(Ra) * inv_s
    y_sigma = J[6] + t.dot(Ra) * inv_s
    return ti.Vector([y_tau[0], y_tau[1], y_tau[2], y_phi[0], y_phi[1], y_phi[2], y_sigma])


@ti.func
def sim3_retract(T, xi):
    """Exp(xi) · T with the quaternion re-normalised."""
    out = sim3_mul(sim3_exp(xi), T)
    return pack(trans(out), quat_normalize(quat(out)), out[7])
