"""``@ti.func`` pieces of tracking and the backend: per-pixel residual rows, their Jacobians,
the Huber weight, and the f64 accumulation of ``W J J^T``; the maths is in
``mslam_ref.tracking``, ``mslam_ref.calib`` and ``mslam_ref.backend``.

The callers' pixel loops are branch-free (``ti.select``, ``&``; a rejected pixel gets a safe
point and weight 0, so it adds exact zeros) so that LLVM vectorises them; hence ``log_pos``
(libm's ``log`` would keep the loop scalar) and the closed-form ray block ``accumulate_rays``.

Accumulator layout (a 36-vector of f64): the upper triangle of the symmetric 7x7 ``H`` row by
row (28 entries, :data:`TRI`), then the 7 entries of ``g``, then the cost.
"""

import taichi as ti

from mslam_fast._types import template

#: (row, col) of the 28 upper-triangle entries of a 7x7 matrix, row-major.
TRI = tuple((a, b) for a in range(7) for b in range(a, 7))
NACC = 36
#: Huber threshold (tracking.huber default; hard-coded in upstream's backend kernels).
HUBER_K = 1.345


#: Pixels per reduction chunk of the tracking and backend kernels (one partial sum each).
CHUNK = 1024


@ti.func
def row(J, r):
    """Row ``r`` of a 7-column matrix as a 7-vector."""
    return ti.Vector([J[r, b] for b in ti.static(range(7))])


@ti.func
def load3(A: template, k):
    """Point k of a flat (3N,) array: the stride 3 is a compile-time constant (a runtime
    (N, 3) shape would make LLVM version the vectorised pixel loop on a stride-1 check that
    fails, falling back to scalar code)."""
    return ti.Vector([A[3 * k], A[3 * k + 1], A[3 * k + 2]])


@ti.func
def huber(x, k):
    """IRLS Huber weight: 1 if |x| < k else k/|x|."""
    a = ti.abs(x)
    return ti.select(a >= k, k / a, 1.0)


@ti.func
def accumulate(acc: template, J, e, Wt, zero: template):
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
def store_acc(out: template, c, acc: template):
    """Row ``c`` of ``out`` <- the 36 accumulators (two static loops of 18: no unroll warning)."""
    for t in ti.static(range(18)):
        out[c, t] = acc[t]
    for t in ti.static(range(18, NACC)):
        out[c, t] = acc[t]


#: Entries known to be zero in each local row type (compile-time sparsity).
ZERO_DIST = (3, 4, 5)
ZERO_CALIB = ((1, 6), (0, 6), (0, 1, 5))
DENSE = ()


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


LN2_HI = 6.93147180369123816490e-01  # ln 2 split in two (fdlibm's e_log.c)
LN2_LO = 1.90821492927058770002e-10
SQRT2 = 1.4142135623730951


@ti.func
def log_pos(x):
    """ln x for a finite normal x > 0, in f64 arithmetic, without a libm call (so it
    vectorises): x = 2^e m with m in [sqrt(1/2), sqrt(2)), s = (m - 1)/(m + 1),
    ln m = 2 (s + s^3/3 + ... + s^19/19) (|s| < 0.172: truncation below 1e-17). Measured error
    vs numpy.log over e^[-30, 30]: 3.4e-16 relative. Returns f64."""
    bits = ti.bit_cast(ti.cast(x, ti.f64), ti.i64)
    ex = (bits >> 52) - 1023
    m = ti.bit_cast(bits - (ex << 52), ti.f64)
    big = m > SQRT2
    m = ti.select(big, m * 0.5, m)
    e = ti.cast(ti.cast(ex, ti.i32) + ti.select(big, 1, 0), ti.f64)
    s = (m - 1.0) / (m + 1.0)
    s2 = s * s
    poly = 0.0 * s
    for i in ti.static(range(9, 0, -1)):
        poly = (poly + 1.0 / (2 * i + 1)) * s2
    return e * LN2_HI + (2.0 * s + (2.0 * s * poly + e * LN2_LO))


@ti.func
def calib_rows(P, fx, fy, cx, cy):
    """``[u, v, log z]`` of P and its local rows ``d[u, v, log z]/d(left perturbation)``
    (3 x 7), for P[2] > 0: no branches (the caller substitutes a safe point such as (0, 0, 1)
    for a rejected pixel), log z by ``log_pos``, so that a pixel loop using it vectorises."""
    iz = 1.0 / P[2]
    xb = P[0] * iz
    yb = P[1] * iz
    J = ti.Matrix(
        [
            [fx * iz, 0.0, -fx * xb * iz, -fx * xb * yb, fx * (1.0 + xb * xb), -fx * yb, 0.0],
            [0.0, fy * iz, -fy * yb * iz, -fy * (1.0 + yb * yb), fy * xb * yb, fy * xb, 0.0],
            [0.0, 0.0, iz, yb, -xb, 0.0, 1.0],
        ]
    )
    logz = ti.cast(log_pos(P[2]), float)
    return ti.Vector([fx * xb + cx, fy * yb + cy, logz]), J


#: Non-zero entries of B = −[p]x, and the identity (compile-time constants).
B_NONZERO = ((False, True, True), (True, False, True), (True, True, False))
EYE3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@ti.func
def accumulate_rays(acc: template, p, inv_d, e, si, hk):
    """acc += the three ray rows (local rows of psi(P), ray a: [(δ_ab − p_a p_b)/d | row a of
    −[p]x | 0], zero at the origin) with errors ``e`` (a 3-vector, the
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
