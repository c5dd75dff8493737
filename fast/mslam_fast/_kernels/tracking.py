"""``@ti.func`` pieces of tracking and the backend: per-pixel residual rows, their Jacobians,
the Huber weight, and the f64 accumulation of ``W J J^T``; the maths is in
``mslam_ref.tracking``, ``mslam_ref.calib`` and ``mslam_ref.backend``.

Accumulator layout (a 36-vector of f64): the upper triangle of the symmetric 7x7 ``H`` row by
row (28 entries, :data:`TRI`), then the 7 entries of ``g``, then the cost.
"""

import taichi as ti

#: (row, col) of the 28 upper-triangle entries of a 7x7 matrix, row-major.
TRI = tuple((a, b) for a in range(7) for b in range(a, 7))
NACC = 36
#: Huber threshold (tracking.huber default; hard-coded in upstream's backend kernels).
HUBER_K = 1.345


@ti.func
def huber(x, k):
    """IRLS Huber weight: 1 if |x| < k else k/|x|."""
    a = ti.abs(x)
    w = 1.0
    if a >= k:
        w = k / a
    return w


@ti.func
def accumulate(acc: ti.template(), J, e, Wt, zero: ti.template()):
    """acc += Wt J J^T (upper triangle), Wt e J, 1/2 Wt e^2 — all in f64 (``J`` a 7-vector,
    ``e`` the residual in the sign convention of the caller). ``zero``: a static tuple of the
    entries of J known to be 0 for this row type (skipped at compile time)."""
    Jd = ti.cast(J, ti.f64)
    wd = ti.cast(Wt, ti.f64)
    ed = ti.cast(e, ti.f64)
    wJ = wd * Jd
    for t in ti.static(range(28)):
        if ti.static(TRI[t][0] not in zero and TRI[t][1] not in zero):
            acc[t] += wJ[TRI[t][0]] * Jd[TRI[t][1]]
    for a in ti.static(range(7)):
        if ti.static(a not in zero):
            acc[28 + a] += ed * wJ[a]
    acc[35] += 0.5 * wd * ed * ed


@ti.func
def store_acc(out: ti.template(), c, acc: ti.template()):
    """Row ``c`` of ``out`` <- the 36 accumulators (two static loops of 18: no unroll warning)."""
    for t in ti.static(range(18)):
        out[c, t] = acc[t]
    for t in ti.static(range(18, NACC)):
        out[c, t] = acc[t]


#: Entries known to be zero in each local row type (compile-time sparsity).
ZERO_RAY = (6,)
ZERO_DIST = (3, 4, 5)
ZERO_CALIB = ((1, 6), (0, 6), (0, 1, 5))
DENSE = ()


@ti.func
def ray_dist_rows(P):
    """Local rows ``d[psi(P), |P|]/d(left perturbation)`` (4 x 7) and ``psi``, ``|P|``.

    ray a: [(delta_ab - psi_a psi_b)/d | row a of -[psi]x | 0];  distance: [psi^T | 0 | d].
    The origin gives zero rows.
    """
    d = P.norm()
    inv_d = 0.0
    if d > 0.0:
        inv_d = 1.0 / d
    p = P * inv_d
    J = ti.Matrix(
        [
            [
                (1.0 - p[0] * p[0]) * inv_d,
                -p[0] * p[1] * inv_d,
                -p[0] * p[2] * inv_d,
                0.0,
                p[2],
                -p[1],
                0.0,
            ],
            [
                -p[1] * p[0] * inv_d,
                (1.0 - p[1] * p[1]) * inv_d,
                -p[1] * p[2] * inv_d,
                -p[2],
                0.0,
                p[0],
                0.0,
            ],
            [
                -p[2] * p[0] * inv_d,
                -p[2] * p[1] * inv_d,
                (1.0 - p[2] * p[2]) * inv_d,
                p[1],
                -p[0],
                0.0,
                0.0,
            ],
            [p[0], p[1], p[2], 0.0, 0.0, 0.0, d],
        ]
    )
    return J, p, d


@ti.func
def unit_and_norm(X):
    d = X.norm()
    inv_d = 0.0
    if d > 0.0:
        inv_d = 1.0 / d
    return X * inv_d, d


@ti.func
def calib_rows(P, fx, fy, cx, cy):
    """``[u, v, log z]`` of P, its local rows ``d[u, v, log z]/d(left perturbation)`` (3 x 7)
    and ``valid_z``; for z <= 0 (the caller applies depth_eps) everything is 0."""
    z = P[2]
    iz = 0.0
    if z > 0.0:
        iz = 1.0 / z
    xb = P[0] * iz
    yb = P[1] * iz
    J = ti.Matrix(
        [
            [fx * iz, 0.0, -fx * xb * iz, -fx * xb * yb, fx * (1.0 + xb * xb), -fx * yb, 0.0],
            [0.0, fy * iz, -fy * yb * iz, -fy * (1.0 + yb * yb), fy * xb * yb, fy * xb, 0.0],
            [0.0, 0.0, iz, yb, -xb, 0.0, 1.0],
        ]
    )
    logz = 0.0
    if z > 0.0:
        logz = ti.log(z)
    else:
        J = ti.Matrix.zero(float, 3, 7)
    return ti.Vector([fx * xb + cx, fy * yb + cy, logz]), J
