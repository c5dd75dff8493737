"""Taichi twin of ``mslam_ref.matching`` — same names, parameters and shapes; see there for the maths.

Parallel axis: target pixels n of image 2, no reductions; on the CPU the LM runs
``LANES_CPU`` = 4 pixels per thread in lockstep (``ti.ndrange(B, ceil(N / 4))``: independent
dependency chains for the out-of-order core), on CUDA one pixel per thread; the refinement
runs one pixel per thread (``ti.ndrange(B, N)``).
``match`` runs everything in one kernel call, so nothing goes back to the host between stages:
loop 1 writes the unit rays into a (B, H, W, 9) scratch image, loop 2 their Scharr gradients,
loops 3 and 4 cast the descriptors to the runtime type into zeroed scratch rows (image 1 with a
border of radius·dilation_max zero pixels, F padded to a multiple of 8; of image 2 only the
pixels with a point, the only ones refined), loop 5 runs the LM
(10 iterations, all taps of the 9-channel image per sample, the accepted sample re-used by the
next iteration), the truncation and distance test, and writes the truncated positions to
``idx``; loop 6 (only if radius > 0) refines them in place, skipping pixels whose own point is
zero (245 dot products of length F; the
7 candidates of a column share one vectorised loop over F, and the zero border replaces the
inside-image test). ``radius`` is a compile-time constant of the
kernels (one compilation per value).

Precision: everything follows the runtime float type (f64 or f32), descriptors included
(upstream uses fp16 for the refinement). The descriptor dot products are summed in vector lanes
(LLVM reassociates them), so they differ from NumPy's in the last bits; only near-ties of two
candidates can then resolve differently.
"""

from collections.abc import Callable
from typing import Any

import numpy as np
import taichi as ti

from mslam_fast import _matching_host as host
from mslam_fast._kernels import matching as K
from mslam_fast._runtime import ensure_init
from mslam_fast._types import nd, template
from mslam_ref.matching import MatchingConfig
from mslam_ref.matching_inputs import check_match_inputs, image_batch, int_pixels

__all__ = [
    "iter_proj",
    "match",
    "ray_image_and_gradients",
    "refine_matches",
]

Array = np.ndarray[Any, Any]
LANES_CPU = 4  # pixels per CPU thread in the LM (lockstep, see K.lm_lanes); 1 on CUDA


def _lanes() -> int:
    """Pixels per thread of the LM: ``LANES_CPU`` on the CPU, 1 on CUDA (one thread per pixel,
    like upstream's kernel: a GPU hides latency with more threads, not with lanes)."""
    return LANES_CPU if ensure_init().arch == "cpu" else 1


# --- kernels -------------------------------------------------------------------------------


@ti.func
def _ray_image(X: template, RG: template):
    """Loops 1 and 2: unit rays into RG[..., 0:3], then their Scharr gradients into 3:9."""
    B, H, W = X.shape[0], X.shape[1], X.shape[2]
    for b, v, u in ti.ndrange(B, H, W):
        R = K.normalize3(K.load3(X, b, v, u))
        for c in ti.static(range(3)):
            RG[b, v, u, c] = R[c]
    for b, v, u in ti.ndrange(B, H, W):
        for c in ti.static(range(3)):
            gx, gy = K.scharr_at(RG, b, v, u, H, W, c)
            RG[b, v, u, 3 + c] = gx
            RG[b, v, u, 6 + c] = gy


@ti.kernel
def _rays_k(X: nd, RG: nd):
    _ray_image(X, RG)


@ti.func
def _targets(X21: template, b, g, N, L: template):
    """Unit targets of pixels g·L .. g·L + L − 1 (clamped to N − 1) as an (L, 3) matrix."""
    T = ti.Matrix([[0.0] * 3 for _ in ti.static(range(L))])
    for l in ti.static(range(L)):
        n = ti.min(g * L + l, N - 1)
        t = K.normalize3(ti.Vector([X21[b, n, 0], X21[b, n, 1], X21[b, n, 2]]))
        for c in ti.static(range(3)):
            T[l, c] = t[c]
    return T


@ti.kernel
def _iter_proj_k(
    RG: nd,
    X21: nd,
    P0: nd,
    P: nd,
    conv: nd,
    max_iter: ti.i32,
    lam0: float,
    thresh: float,
    lanes: template,
):
    H, W = RG.shape[1], RG.shape[2]
    N = X21.shape[1]
    for b, g in ti.ndrange(X21.shape[0], (N + lanes - 1) // lanes):
        T = _targets(X21, b, g, N, lanes)
        u0 = ti.Vector([0.0] * lanes)
        v0 = ti.Vector([0.0] * lanes)
        for l in ti.static(range(lanes)):
            n = ti.min(g * lanes + l, N - 1)
            u0[l], v0[l] = P0[b, n, 0], P0[b, n, 1]
        u, v, c = K.lm_lanes(RG, b, T, u0, v0, H, W, max_iter, lam0, thresh, lanes)
        for l in ti.static(range(lanes)):
            n = g * lanes + l
            if n < N:
                P[b, n, 0] = u[l]
                P[b, n, 1] = v[l]
                conv[b, n] = ti.cast(c[l], ti.u8)


@ti.func
def _copy_rows(D: template, Dp: template):
    """Rows of ``D (M, F)`` (any float type) into the zeroed ``Dp (M, Fp)`` (runtime type)."""
    for r, k in ti.ndrange(D.shape[0], D.shape[1]):
        Dp[r, k] = ti.cast(D[r, k], float)


@ti.kernel
def _refine_k(
    D11: nd,
    D21: nd,
    D1p: nd,
    D2p: nd,
    P1: nd,
    out: nd,
    H: ti.i32,
    W: ti.i32,
    radius: template,
    dmax: ti.i32,
):
    K.pad_descriptors(D11, D1p, H, W, radius * dmax)
    _copy_rows(D21, D2p)
    for b, n in ti.ndrange(P1.shape[0], P1.shape[1]):
        u, v = K.refine_pixel(
            D1p,
            D2p,
            b,
            b * P1.shape[1] + n,
            ti.cast(P1[b, n, 0], ti.i32),
            ti.cast(P1[b, n, 1], ti.i32),
            H,
            W,
            radius,
            dmax,
        )
        out[b, n, 0] = u
        out[b, n, 1] = v


@ti.kernel
def _match_k(
    X11: nd,
    X21: nd,
    D11: nd,
    D21: nd,
    D1p: nd,
    D2p: nd,
    idx0: nd,
    use_init: ti.i32,
    RG: nd,
    idx: nd,
    valid: nd,
    max_iter: ti.i32,
    lam0: float,
    thresh: float,
    dist_thresh: float,
    radius: template,
    dmax: ti.i32,
    lanes: template,
):
    _ray_image(X11, RG)
    H, W = X11.shape[1], X11.shape[2]
    K.pad_descriptors(D11, D1p, H, W, radius * dmax)  # top level (parallel): no `if radius > 0`
    N = H * W
    for r, k in ti.ndrange(D21.shape[0], D21.shape[1]):  # rows of pixels with a point only
        b, n = r // N, r % N
        if X21[b, n, 0] != 0.0 or X21[b, n, 1] != 0.0 or X21[b, n, 2] != 0.0:
            D2p[r, k] = ti.cast(D21[r, k], float)
    for b, g in ti.ndrange(X21.shape[0], (N + lanes - 1) // lanes):
        T = _targets(X21, b, g, N, lanes)
        u0 = ti.Vector([0.0] * lanes)
        v0 = ti.Vector([0.0] * lanes)
        for l in ti.static(range(lanes)):
            i0 = ti.min(g * lanes + l, N - 1)
            if use_init != 0:
                i0 = ti.cast(idx0[b, i0], ti.i32)
            u0[l], v0[l] = ti.cast(i0 % W, float), ti.cast(i0 // W, float)
        u_f, v_f, conv = K.lm_lanes(RG, b, T, u0, v0, H, W, max_iter, lam0, thresh, lanes)
        for l in ti.static(range(lanes)):
            n = g * lanes + l
            if n < N:
                u, v = ti.cast(u_f[l], ti.i32), ti.cast(v_f[l], ti.i32)  # truncation (>= 1)
                X2 = ti.Vector([X21[b, n, 0], X21[b, n, 1], X21[b, n, 2]])
                X1 = K.load3(X11, b, v, u)
                d = X1 - X2
                ok = (
                    conv[l] != 0
                    and ti.sqrt(K.dot3(d, d)) < dist_thresh
                    and ti.sqrt(K.dot3(X2, X2)) > K.NORM_EPS
                    and ti.sqrt(K.dot3(X1, X1)) > K.NORM_EPS
                )
                idx[b, n] = ti.cast(u, ti.i64) + ti.cast(W, ti.i64) * ti.cast(v, ti.i64)
                valid[b, n] = ti.cast(1 if ok else 0, ti.u8)
    if ti.static(radius > 0):  # loop 6: refinement from the truncated LM positions in idx
        for b, n in ti.ndrange(X21.shape[0], N):
            X2 = ti.Vector([X21[b, n, 0], X21[b, n, 1], X21[b, n, 2]])
            if ti.sqrt(K.dot3(X2, X2)) > K.NORM_EPS:  # a pixel without a point is not refined
                u, v = K.refine_pixel(
                    D1p,
                    D2p,
                    b,
                    b * N + n,
                    ti.cast(idx[b, n] % W, ti.i32),
                    ti.cast(idx[b, n] // W, ti.i32),
                    H,
                    W,
                    radius,
                    dmax,
                )
                idx[b, n] = ti.cast(u, ti.i64) + ti.cast(W, ti.i64) * ti.cast(v, ti.i64)


# --- host wrappers -------------------------------------------------------------------------


def ray_image_and_gradients(X11: Any) -> Array:
    """Taichi twin of ``mslam_ref.matching.ray_image_and_gradients`` (two parallel loops)."""
    X, _ = image_batch(X11, "X11", 3)
    X = host.points(X)
    RG = np.empty((*X.shape[:-1], 9), dtype=X.dtype)
    if X.shape[0] > 0:
        _rays_k(X, RG)
    return RG.reshape(*np.shape(X11)[:-1], 9)


def iter_proj(
    rays_with_grad: Any,
    X21: Any,
    p_init: Any,
    cfg: MatchingConfig = MatchingConfig(),  # noqa: B008 (frozen, immutable)
) -> tuple[Array, Array]:
    """Taichi twin of ``mslam_ref.matching.iter_proj`` (``_lanes()`` target pixels per thread)."""
    RG, batched = image_batch(rays_with_grad, "rays_with_grad", 9)
    RG = host.as_runtime_float(RG, "rays_with_grad")
    B = RG.shape[0]
    lead = (B,) if batched else ()
    t = np.asarray(X21)
    if t.ndim != len(lead) + 2 or t.shape[:-2] != lead or t.shape[-1] != 3:
        raise ValueError(f"X21: expected shape (N, 3), or (B, N, 3) with B={B}, got {t.shape}")
    p0 = np.asarray(p_init)
    if p0.shape != (*t.shape[:-1], 2):
        raise ValueError(f"p_init: expected shape {(*t.shape[:-1], 2)}, got {p0.shape}")
    N = t.shape[-2]
    t = host.points(t).reshape(B, N, 3)
    p0 = host.as_runtime_float(p0, "p_init").reshape(B, N, 2)
    P = np.empty_like(p0)
    conv = np.zeros(p0.shape[:-1], dtype=np.uint8)
    if P.size:
        _iter_proj_k(
            RG,
            t,
            p0,
            P,
            conv,
            int(cfg.max_iter),
            float(cfg.lambda_init),
            float(cfg.convergence_thresh),
            _lanes(),
        )
    return (P, host.flags(conv)) if batched else (P[0], host.flags(conv[0]))


def refine_matches(
    D11: Any,
    D21: Any,
    p1: Any,
    cfg: MatchingConfig = MatchingConfig(),  # noqa: B008 (frozen, immutable)
) -> Array:
    """Taichi twin of ``mslam_ref.matching.refine_matches`` (245 vectorised dot products/thread)."""
    D1, batched = image_batch(D11, "D11", None)
    B, H, W, F = D1.shape
    lead = (B,) if batched else ()
    D2 = np.asarray(D21)
    if D2.ndim != len(lead) + 2 or D2.shape[:-2] != lead or D2.shape[-1] != F:
        raise ValueError(f"D21: expected shape (N, {F}) or (B, N, {F}), got {D2.shape}")
    N = D2.shape[-2]
    p = int_pixels(p1, "p1", (*D2.shape[:-1], 2), H, W).reshape(B, N, 2)
    D1, D2 = host.descriptors(D1.reshape(-1, F), "D11"), host.descriptors(D2.reshape(-1, F), "D21")
    out = np.empty_like(p)
    if out.size:
        radius, dmax = int(cfg.radius), int(cfg.dilation_max)
        D1p, D2p = host.scratch(B, H, W, F, N, max(radius * dmax, 0))
        _refine_k(D1, D2, D1p, D2p, p, out, H, W, radius, dmax)
    return out if batched else out[0]


def _match_args(
    X11: Any,
    X21: Any,
    D11: Any,
    D21: Any,
    idx_init: Any,
    cfg: MatchingConfig,
    D2_kept: Callable[[Array], Any] | None = None,
) -> tuple[tuple[Any, ...], bool]:
    """Checked and converted arguments of ``_match_k`` (host arrays; ``idx`` and ``valid`` at
    positions 9 and 10 are its outputs) and whether the inputs had a batch axis.

    Split from :func:`match` so that ``benchmarks/bench_matching.py`` can time the kernel alone
    on copies held in ``ti.ndarray``s (on the GPU for CUDA: the way upstream's figure is
    measured), and so that ``mslam_fast.resident`` can pass ``D21`` as a device array it keeps:
    ``D2_kept(D2)`` receives the (B·N, F) host descriptors, unchecked, and returns their checked
    device form.
    """
    X1, X2, D1, D2, idx0, batched = check_match_inputs(X11, X21, D11, D21, idx_init)
    B, H, W, F = D1.shape
    N = H * W
    if idx0 is None:
        idx0 = np.zeros((1, 1), dtype=np.int64)  # unused by the kernel (use_init = 0)
    X1, X2 = host.points(X1), host.points(X2).reshape(B, N, 3)
    D1 = host.descriptors(D1.reshape(B * N, F), "D11")
    if D2_kept is None or cfg.radius <= 0:
        D2 = host.descriptors(D2.reshape(B * N, F), "D21")
    else:
        D2 = D2_kept(D2.reshape(B * N, F))
    if cfg.radius > 0:
        D1p, D2p = host.scratch(B, H, W, F, N, int(cfg.radius) * int(cfg.dilation_max))
    else:  # no refinement: one-row stand-ins, so the kernel's copy loops are trivial
        D1 = D2 = np.zeros((1, F), X1.dtype)
        D1p, D2p = host.scratch(1, 1, 1, F, 1, 0)
    args = (
        X1,
        X2,
        D1,
        D2,
        D1p,
        D2p,
        idx0,
        int(idx_init is not None),
        host.ray_scratch(B, H, W),  # RG scratch
        np.empty((B, N), dtype=np.int64),  # idx (output)
        np.empty((B, N), dtype=np.uint8),  # valid (output)
        int(cfg.max_iter),
        float(cfg.lambda_init),
        float(cfg.convergence_thresh),
        float(cfg.dist_thresh),
        int(cfg.radius),
        int(cfg.dilation_max),
        _lanes(),
    )
    return args, batched


def match(
    X11: Any,
    X21: Any,
    D11: Any,
    D21: Any,
    idx_init: Any = None,
    cfg: MatchingConfig = MatchingConfig(),  # noqa: B008 (frozen, immutable)
) -> tuple[Array, Array]:
    """Taichi twin of ``mslam_ref.matching.match`` (one fused kernel: rays, gradients, LM,
    truncation, distance test, refinement)."""
    args, batched = _match_args(X11, X21, D11, D21, idx_init, cfg)
    idx, valid = args[9], args[10]
    if idx.shape[0] > 0:
        _match_k(*args)
    return (idx, host.flags(valid)) if batched else (idx[0], host.flags(valid[0]))
