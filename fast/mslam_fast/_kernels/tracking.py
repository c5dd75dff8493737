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
    return ti.select(a >= k, k / a, 1.0)


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
    p, d, inv_d = unit_norm_inv(P)
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
def unit_norm_inv(X):
    """psi(X), |X| and 1/|X| (0 at the origin)."""
    d = X.norm()
    inv_d = ti.select(d > 0.0, 1.0 / d, 0.0)
    return X * inv_d, d, inv_d


@ti.func
def unit_and_norm(X):
    d = X.norm()
    inv_d = ti.select(d > 0.0, 1.0 / d, 0.0)
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


#: Non-zero entries of B = −[p]x; the identity; the two other axes of each axis.
B_NONZERO = ((False, True, True), (True, False, True), (True, True, False))
EYE3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
OTHERS = ((1, 2), (0, 2), (0, 1))


@ti.func
def accumulate_rays(acc: ti.template(), p, inv_d, e, si, hk):
    """acc += the three ray rows of ``ray_dist_rows`` with errors ``e`` (a 3-vector, the
    caller's sign), sqrt information ``si`` and per-row Huber weights w_a, in closed form (f64).

    With A = (I − p pᵀ)/d, B = −[p]x (rows a of the ray Jacobian: [A_a | B_a | 0]), W = diag(w)
    and m = Σ_r w_r p_r², c = Bᵀ W p, ε = W e:
        (A W A)_ij = (w_i δ_ij − (w_i + w_j − m) p_i p_j)/d²,   (A W B)_ij = (w_i B_ij − p_i c_j)/d,
        (Bᵀ W B)_ij = Σ_r w_r B_ri B_rj,   g = [(ε − p (pᵀε))/d | Bᵀε = p × ε | 0],
    cost Σ_a w_a e_a² / 2: one row's worth of accumulation instead of three.
    """
    w = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
    for a in ti.static(range(3)):
        w[a] = ti.cast(si * si * huber(si * e[a], hk), ti.f64)
    pd = ti.cast(p, ti.f64)
    ed = ti.cast(e, ti.f64)
    idd = ti.cast(inv_d, ti.f64)
    B = ti.Matrix([[0.0, pd[2], -pd[1]], [-pd[2], 0.0, pd[0]], [pd[1], -pd[0], 0.0]], dt=ti.f64)
    m = w[0] * pd[0] * pd[0] + w[1] * pd[1] * pd[1] + w[2] * pd[2] * pd[2]
    c = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
    for j in ti.static(range(3)):
        for r in ti.static(range(3)):
            if ti.static(B_NONZERO[r][j]):
                c[j] += w[r] * pd[r] * B[r, j]
    idd2 = idd * idd
    for t in ti.static(range(28)):
        a, b = ti.static(TRI[t][0], TRI[t][1])
        if ti.static(b < 3):
            acc[t] += idd2 * (EYE3[a][b] * w[a] - (w[a] + w[b] - m) * pd[a] * pd[b])
        elif ti.static(a < 3 and b < 6):
            if ti.static(B_NONZERO[a][b - 3]):
                acc[t] += idd * (w[a] * B[a, b - 3] - pd[a] * c[b - 3])
            else:
                acc[t] += -idd * pd[a] * c[b - 3]
        elif ti.static(b < 6):
            v = 0.0 * idd
            for r in ti.static(range(3)):
                if ti.static(B_NONZERO[r][a - 3] and B_NONZERO[r][b - 3]):
                    v += w[r] * B[r, a - 3] * B[r, b - 3]
            acc[t] += v
    eps = w * ed
    pe = pd[0] * eps[0] + pd[1] * eps[1] + pd[2] * eps[2]
    for a in ti.static(range(3)):
        acc[28 + a] += idd * (eps[a] - pd[a] * pe)
    pxe = pd.cross(eps)
    for a in ti.static(range(3)):
        acc[31 + a] += pxe[a]
    acc[35] += 0.5 * (eps[0] * ed[0] + eps[1] * ed[1] + eps[2] * ed[2])
