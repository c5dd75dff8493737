"""``@ti.func`` building blocks of pointmap matching; the maths is in ``mslam_ref.matching``.

One Taichi thread runs the Levenberg–Marquardt on the pixel positions of L target pixels of
image 2 in lockstep (``lm_lanes``), then truncation and the 3-D distance test (in the fused
kernel of ``mslam_fast.matching``); a second loop refines one pixel per thread
(``refine_pixel``). Every arithmetic
expression is written in the order of the NumPy reference (dot products of 3-vectors as
``a0 b0 + a1 b1 + a2 b2``, bilinear taps in the order 00, 10, 01, 11) so that float64 runs
agree bit for bit up to LLVM's fused multiply-adds.

Arrays (Taichi ndarrays): ray image ``RG (B, H, W, 9)`` = [R, gx, gy]; points ``(B, H, W, 3)``
or ``(B, N, 3)``; descriptors as zero-padded rows (F -> Fp, a multiple of 8): image 1 with a
border of P = radius·dilation_max zero pixels, ``D11 (B·(H+2P)·(W+2P), Fp)`` (written by
``pad_descriptors``), and ``D21 (B·N, Fp)``.
"""

import taichi as ti

from mslam_fast._types import template

NORM_EPS = 1e-12  # F.normalize eps, as mslam_ref.matching.NORM_EPS
DET_MIN = 1e-30  # 2x2 determinant below which the LM step is zero, as mslam_ref.matching.DET_MIN


@ti.func
def dot3(a, b):
    """a0 b0 + a1 b1 + a2 b2 (the reference's ``_dot3`` order)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@ti.func
def normalize3(x):
    """x / max(‖x‖, 1e-12): F.normalize; a zero vector stays zero."""
    return x / ti.max(ti.sqrt(dot3(x, x)), NORM_EPS)


@ti.func
def load3(A: template, b, i, j):
    """A[b, i, j, 0:3] as a 3-vector (a point of a (B, H, W, 3) array)."""
    return ti.Vector([A[b, i, j, 0], A[b, i, j, 1], A[b, i, j, 2]])


@ti.func
def reflect(i, n):
    """Index of reflect padding by one pixel: -1 -> 1, n -> n - 2."""
    j = i
    if i < 0:
        j = 1
    elif i > n - 1:
        j = n - 2
    return j


@ti.func
def scharr_at(R: template, b, v, u, H, W, c):
    """Scharr gx, gy (1/32, cross-correlation, reflect padding) of channel c of R at (v, u)."""
    um, up = reflect(u - 1, W), reflect(u + 1, W)
    vm, vp = reflect(v - 1, H), reflect(v + 1, H)
    gx = (
        3.0 * (R[b, vm, up, c] - R[b, vm, um, c])
        + 10.0 * (R[b, v, up, c] - R[b, v, um, c])
        + 3.0 * (R[b, vp, up, c] - R[b, vp, um, c])
    ) / 32.0
    gy = (
        3.0 * (R[b, vp, um, c] - R[b, vm, um, c])
        + 10.0 * (R[b, vp, u, c] - R[b, vm, u, c])
        + 3.0 * (R[b, vp, up, c] - R[b, vm, up, c])
    ) / 32.0
    return gx, gy


@ti.func
def sample9(RG: template, b, u, v):
    """Bilinear sample of all 9 channels of RG at (u, v) (0 <= u <= W-2, 0 <= v <= H-2)."""
    fu, fv = ti.floor(u), ti.floor(v)
    iu, iv = ti.cast(fu, ti.i32), ti.cast(fv, ti.i32)
    du, dv = u - fu, v - fv
    w00 = (1.0 - du) * (1.0 - dv)
    w10 = du * (1.0 - dv)
    w01 = (1.0 - du) * dv
    w11 = du * dv
    out = ti.Vector([0.0] * 9)
    for c in ti.static(range(9)):
        out[c] = (
            w00 * RG[b, iv, iu, c]
            + w10 * RG[b, iv, iu + 1, c]
            + w01 * RG[b, iv + 1, iu, c]
            + w11 * RG[b, iv + 1, iu + 1, c]
        )
    return out


@ti.func
def ray_cost(S, t):
    """‖normalize(S[0:3]) − t‖² and the error vector e."""
    r = normalize3(ti.Vector([S[0], S[1], S[2]]))
    e = r - t
    return dot3(e, e), e


@ti.func
def clamp(x, lo, hi):
    """min(max(x, lo), hi), as np.clip."""
    return ti.min(ti.max(x, lo), hi)


@ti.func
def lm_lanes(RG: template, b, T, u_init, v_init, H, W, max_iter, lam0, thresh, L: template):
    """Per-pixel LM of ``mslam_ref.matching.iter_proj`` for L pixels in lockstep.

    ``T (L, 3)`` holds the unit targets, ``u_init``/``v_init`` the L starts; returns the L-vectors
    (u, v, converged). Each pixel's iterations form one long dependency chain (sample, cost,
    2x2 solve, sample), so a single pixel leaves the core waiting on latencies; the L
    independent chains of one iteration sit side by side in the instruction stream for the
    out-of-order core to overlap. Accept/reject and the singular-system test are branch-free
    (``ti.select``) with the reference's values: a lane with a zero target keeps its clamped
    start and ``converged = 0`` (the reference runs no iteration for it).
    """
    u = ti.Vector([0.0] * L)
    v = ti.Vector([0.0] * L)
    lam = ti.Vector([0.0] * L)
    conv = ti.Vector([0] * L)
    act = ti.Vector([0] * L)
    S = ti.Matrix([[0.0] * 9 for _ in ti.static(range(L))])
    for l in ti.static(range(L)):
        u[l] = clamp(u_init[l], 1.0, W - 2.0)
        v[l] = clamp(v_init[l], 1.0, H - 2.0)
        lam[l] = lam0
        t = ti.Vector([T[l, 0], T[l, 1], T[l, 2]])
        act[l] = 1 if ti.sqrt(dot3(t, t)) > NORM_EPS else 0
        S0 = sample9(RG, b, u[l], v[l])
        for c in ti.static(range(9)):
            S[l, c] = S0[c]
    n_iter = max_iter if act.sum() > 0 else 0  # a group of zero targets runs no iteration
    for _ in range(n_iter):
        for l in ti.static(range(L)):
            t = ti.Vector([T[l, 0], T[l, 1], T[l, 2]])
            Sl = ti.Vector([S[l, c] for c in ti.static(range(9))])
            cost, e = ray_cost(Sl, t)
            gx = ti.Vector([Sl[3], Sl[4], Sl[5]])
            gy = ti.Vector([Sl[6], Sl[7], Sl[8]])
            A00 = dot3(gx, gx) + lam[l]
            A01 = dot3(gx, gy)
            A11 = dot3(gy, gy) + lam[l]
            b0 = -dot3(e, gx)
            b1 = -dot3(e, gy)
            det = A00 * A11 - A01 * A01
            ok = det > DET_MIN  # §3.2: closed-form 2x2 solve of (JᵀJ + λI) δ = −Jᵀe
            det_s = ti.select(ok, det, 1.0)
            du = ti.select(ok, (A11 * b0 - A01 * b1) / det_s, 0.0)
            dv = ti.select(ok, (A00 * b1 - A01 * b0) / det_s, 0.0)
            u_new = clamp(u[l] + du, 1.0, W - 2.0)
            v_new = clamp(v[l] + dv, 1.0, H - 2.0)
            S_new = sample9(RG, b, u_new, v_new)
            new_cost, _e = ray_cost(S_new, t)
            better = new_cost < cost
            acc = better and act[l] != 0
            u[l] = ti.select(acc, u_new, u[l])
            v[l] = ti.select(acc, v_new, v[l])
            for c in ti.static(range(9)):
                S[l, c] = ti.select(acc, S_new[c], S[l, c])
            lam[l] = ti.select(better, lam[l] * 0.1, lam[l] * 10.0)
            c_it = ti.select(better, new_cost < thresh, cost < thresh)
            conv[l] = ti.select(act[l] != 0, ti.cast(c_it, ti.i32), conv[l])
    return u, v, conv


@ti.func
def pad_descriptors(D: template, Dp: template, H, W, pad):
    """Copy the rows of ``D (B·H·W, F)`` (any float type) into ``Dp (B·Hp·Wp, Fp)`` (runtime
    float type), the rows of an image with a border of ``pad`` pixels (Hp = H + 2 pad,
    Wp = W + 2 pad); ``Dp`` arrives zeroed, so its border and its columns F..Fp stay 0."""
    Hp, Wp = H + 2 * pad, W + 2 * pad
    for r in range(D.shape[0]):
        b = r // (H * W)
        v = (r % (H * W)) // W
        u = r % W
        rp = (b * Hp + v + pad) * Wp + u + pad
        for k in range(D.shape[1]):
            Dp[rp, k] = ti.cast(D[r, k], float)


@ti.func
def refine_pixel(
    D11: template,
    D21: template,
    b,
    row2,
    u_start,
    v_start,
    H,
    W,
    radius: template,
    dmax,
):
    """Coarse-to-fine descriptor search of ``mslam_ref.matching.refine_matches``; returns (u, v).

    ``D11`` holds the rows ``(B·(H + 2P)·(W + 2P), Fp)`` of image-1 descriptors with a border
    of P = radius·dmax zero descriptors, ``D21`` is ``(B·N, Fp)``; the target's row is ``row2``
    and image 1 is batch element ``b``. A candidate outside the image reads a zero descriptor
    and scores exactly 0, which never beats ``best >= 0`` under the strict ``>``: the
    reference's inside-image test, without a branch. ``radius`` is a compile-time constant:
    the 2·radius + 1 candidates of one column (fixed u offset) are scored together in one
    runtime-length loop over Fp (zero-padded F) with one accumulator each, which LLVM's loop
    vectoriser turns into SIMD code (the target's descriptor is loaded once per column, the
    loop overhead is shared); they are then compared in the reference's order (v offset
    inner), branch-free. ``best`` starts at 0.0 (``REFINE_BEST_INIT``).
    """
    Fp = D11.shape[1]
    P = radius * dmax
    Hp, Wp = H + 2 * P, W + 2 * P
    best = D21[row2, 0] * 0.0
    u0, v0 = u_start, v_start
    ub, vb = u_start, v_start
    for level in range(dmax):
        d = dmax - level
        rd = radius * d
        for i in range(2 * radius + 1):  # u offset, outer (upstream loop order)
            u = u0 - rd + i * d
            row0 = (b * Hp + v0 - rd + P) * Wp + u + P  # candidate j = 0 of this column
            step = d * Wp
            s = ti.Vector([0.0] * (2 * radius + 1))
            for k in range(Fp):
                q = D21[row2, k]
                for j in ti.static(range(2 * radius + 1)):
                    s[j] += q * D11[row0 + j * step, k]
            for j in ti.static(range(2 * radius + 1)):
                better = s[j] > best  # branch-free update (an unpredictable branch otherwise)
                best = ti.select(better, s[j], best)
                ub = ti.select(better, u, ub)
                vb = ti.select(better, v0 - rd + j * d, vb)
        u0, v0 = ub, vb
    return ub, vb
