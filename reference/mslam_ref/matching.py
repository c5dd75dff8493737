"""Paper §3.2 — Pointmap matching: iterative projective matching and descriptor refinement.

For every pixel n of image 2 we know a 3-D point ``X21[n]`` expressed in camera 1 (MASt3R's
second pointmap of the pair). Its match in image 1 is the pixel p whose *ray* ``ψ(X11[p]) =
X11[p] / ‖X11[p]‖`` points the same way as ``ψ(X21[n])``. Instead of a nearest-neighbour search
over all rays, each target pixel runs a small Levenberg–Marquardt on its pixel position (u, v)
in the ray image of camera 1, starting from an initial guess (the identity, or the previous
frame's matches). The integer match then gets a 3-D distance (occlusion) test and is refined by
a coarse-to-fine search for the best descriptor similarity around it.

    p*(n) = argmin_p ‖ψ(X11(p)) − ψ(X21[n])‖²                   (§3.2 Eq. 2, LM over p)
    valid = converged ∧ ‖X11[⌊p*⌋] − X21[n]‖ < dist_thresh       (occlusion test)
    p(n)  = argmax_{p ∈ window(⌊p*⌋)} D21[n] · D11[p]            (descriptor refinement)

Upstream: mast3r_slam/matching.py (match, match_iterative_proj, prep_for_iter_proj),
mast3r_slam/image.py::img_gradient, mast3r_slam/backend/src/matching_kernels.cu
(iter_proj_kernel, refine_matches_kernel). Quirks reproduced on purpose (docs/upstream.md §4, §15.4):
truncation (not rounding) of the sub-pixel match, clamping to [1, W−2] × [1, H−2], the
unnormalised-gradient Jacobian, the distance test before refinement, and ``best ≈ 0`` at the
start of refinement (we take exactly 0.0; see :func:`refine_matches`).

Points that are zero or non-finite are accepted and treated as "no point": their unit ray is
the zero vector (``F.normalize`` with eps 1e-12 does the same for zero), and any target pixel
whose own point, or whose match's point, is such a point is marked invalid. No NaN escapes.

Public names, in reading order:
    MatchingConfig, normalize, scharr_gradients, ray_image_and_gradients, bilinear_sample,
    iter_proj, refine_matches, match
(``scharr_gradients`` and ``bilinear_sample`` live in ``mslam_ref.image_ops``, the shape checks
in ``mslam_ref.matching_inputs``.)
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from mslam_ref.conventions import BoolArray, FloatArray, IntArray, as_float_array
from mslam_ref.image_ops import bilinear_sample, scharr_gradients
from mslam_ref.matching_inputs import check_match_inputs, image_batch, int_pixels

__all__ = [
    "DET_MIN",
    "NORM_EPS",
    "REFINE_BEST_INIT",
    "MatchingConfig",
    "bilinear_sample",
    "iter_proj",
    "match",
    "normalize",
    "ray_image_and_gradients",
    "refine_matches",
    "scharr_gradients",
]

#: eps of ``F.normalize``: ``x / max(‖x‖, eps)``.
NORM_EPS = 1e-12

#: Initial best score of the refinement. Upstream: ``numeric_limits<at::Half>::min()``, which is
#: 0 for an unspecialised ``numeric_limits`` or 6.1e-5 for a specialised half (docs/upstream.md §16.6). We
#: take 0.0: only candidates with a strictly positive cosine similarity can move a match.
REFINE_BEST_INIT = 0.0

#: 2x2 LM determinant at or below which the step is zero. det >= λ² > 0 in exact arithmetic, so
#: this only catches rounding (f32) and regions of zero gradient; it keeps every step finite.
DET_MIN = 1e-30


@dataclasses.dataclass(frozen=True)
class MatchingConfig:
    """``matching:`` block of upstream's config/base.yaml (docs/upstream.md §11), upstream key names.

    Attributes:
        max_iter: LM iterations per pixel, all of them run (no early exit).
        lambda_init: initial LM damping λ.
        convergence_thresh: a pixel converged when its squared ray error ‖e‖² is below this
            (1e-6 is an angle of about 1e-3 rad, since ‖ψ1 − ψ2‖² = 2 (1 − cos θ)).
        dist_thresh: 3-D occlusion test ‖X11[p] − X21[n]‖ < dist_thresh (pointmap units).
        radius: refinement half-window in dilated steps; 0 switches refinement off.
        dilation_max: refinement levels d = dilation_max, ..., 1.
    """

    max_iter: int = 10
    lambda_init: float = 1e-8
    convergence_thresh: float = 1e-6
    dist_thresh: float = 0.1
    radius: int = 3
    dilation_max: int = 5

    def __post_init__(self) -> None:
        for name in ("max_iter", "radius", "dilation_max"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, int | np.integer) or val < 0:
                raise ValueError(f"MatchingConfig.{name}: expected an int >= 0, got {val!r}")
        if self.dilation_max < 1:
            raise ValueError(f"MatchingConfig.dilation_max: must be >= 1, got {self.dilation_max}")
        for name in ("lambda_init", "convergence_thresh", "dist_thresh"):
            val = float(getattr(self, name))
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"MatchingConfig.{name}: must be finite and > 0, got {val!r}")


# --- small helpers ----------------------------------------------------------------------------


def _dot3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Dot product over the last axis of 3-vectors, in a fixed order (the fast twin's order)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def normalize(X: Any) -> FloatArray:
    """Unit vectors ``x / max(‖x‖, 1e-12)`` as ``torch.nn.functional.normalize``.

    Paper: §3.2, ψ(x) = x / ‖x‖. Upstream: matching.py::prep_for_iter_proj (F.normalize).

    Args:
        X: (..., 3) vectors; zero or non-finite vectors map to the zero vector.

    Returns:
        (..., 3) float64, unit or zero.
    """
    X = _points(X, "X")
    return X / np.maximum(np.sqrt(_dot3(X, X)), NORM_EPS)[..., None]


def _points(X: Any, name: str) -> FloatArray:
    """float64 copy of an (..., 3) point array with non-finite points replaced by zero."""
    X = np.array(X, dtype=np.float64)
    if X.ndim < 1 or X.shape[-1] != 3:
        raise ValueError(f"{name}: expected trailing shape (3,), got shape {X.shape}")
    X[~np.all(np.isfinite(X), axis=-1)] = 0.0
    return X


def _point_ok(X: FloatArray) -> BoolArray:
    """True where a (sanitised) point has a defined ray (norm above NORM_EPS)."""
    return np.sqrt(_dot3(X, X)) > NORM_EPS


# --- §4.1 ray image and gradients ------------------------------------------------------------


def ray_image_and_gradients(X11: Any) -> FloatArray:
    """The 9-channel image ``[ψ(X11), ∂ψ/∂u, ∂ψ/∂v]`` that the LM samples.

    Paper: §3.2. Upstream: matching.py::prep_for_iter_proj.

    Args:
        X11: (H, W, 3) or (B, H, W, 3) pointmap of image 1 in camera 1 (zero or non-finite
            points give a zero ray).

    Returns:
        (H, W, 9) or (B, H, W, 9) float64: unit rays R, then gx(R), then gy(R) (Scharr, 1/32).
    """
    X, _ = image_batch(X11, "X11", 3)
    R = normalize(X)
    gx, gy = scharr_gradients(R)
    return np.concatenate([R, gx, gy], axis=-1).reshape(*np.shape(X11)[:-1], 9)


# --- §4.2 per-pixel Levenberg–Marquardt ------------------------------------------------------


def _ray_cost(S: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """‖normalize(sampled ray) − t‖² per pixel; S (..., >=3), t (..., 3)."""
    r = S[..., :3] / np.maximum(np.sqrt(_dot3(S[..., :3], S[..., :3])), NORM_EPS)[..., None]
    e = r - t
    return _dot3(e, e), e


def iter_proj(
    rays_with_grad: Any, X21: Any, p_init: Any, cfg: MatchingConfig = MatchingConfig()
) -> tuple[FloatArray, BoolArray]:
    """Per-pixel Levenberg–Marquardt on the pixel position p = (u, v) in image 1.

    Paper: §3.2 (iterative projective matching). Upstream: matching_kernels.cu::iter_proj_kernel.

        clamp u to [1, W−2], v to [1, H−2];  λ = lambda_init
        repeat max_iter times (no early exit):
            [r̃, gx, gy] = bilinear(rays_with_grad, u, v);  r = r̃ / ‖r̃‖;  e = r − t
            J = [gx gy] (3x2, the gradient of the *unnormalised* interpolated ray)
            δ = (JᵀJ + λ I)⁻¹ (−Jᵀ e)       (closed-form 2x2 solve)
            p' = clamp(p + δ);  cost' = ‖normalize(r̃(p')) − t‖²
            accept if cost' < cost: p = p', λ /= 10, converged = cost' < thresh
            else:                   λ *= 10,          converged = cost  < thresh

    Numerics: a 2x2 determinant <= DET_MIN (1e-30; only from rounding or zero gradients) gives
    δ = 0, so every step is finite; a huge step is clamped to the border like any other. A zero
    target (zero or non-finite point) has cost 1 everywhere: it keeps its clamped start and
    never converges (upstream would let rounding noise move it).

    Args:
        rays_with_grad: (H, W, 9) or (B, H, W, 9) from :func:`ray_image_and_gradients`.
        X21: (N, 3) or (B, N, 3) target points in camera 1 (normalised here; zero or
            non-finite points get a zero target).
        p_init: (N, 2) or (B, N, 2) initial (u, v), any finite values (clamped).
        cfg: uses ``max_iter``, ``lambda_init``, ``convergence_thresh``.

    Returns:
        p: (N, 2) or (B, N, 2) float64 final (u, v), inside [1, W−2] x [1, H−2].
        converged: (N,) or (B, N) bool.
    """
    RG, batched = image_batch(rays_with_grad, "rays_with_grad", 9)
    RG = as_float_array(RG, "rays_with_grad")
    B, H, W, _ = RG.shape
    lead = (B,) if batched else ()
    t = normalize(_points(X21, "X21"))
    p0 = as_float_array(p_init, "p_init", 2)
    if t.ndim != len(lead) + 2 or t.shape[:-2] != lead:
        raise ValueError(f"X21: expected shape (N, 3), or (B, N, 3) with B={B}, got {t.shape}")
    if p0.shape != (*t.shape[:-1], 2):
        raise ValueError(f"p_init: expected shape {(*t.shape[:-1], 2)}, got {p0.shape}")
    N = t.shape[-2]
    t, p0 = t.reshape(B, N, 3), p0.reshape(B, N, 2)
    has_ray = _point_ok(t)  # a zero target (zero or non-finite point) keeps its start
    u = np.clip(p0[..., 0], 1.0, W - 2.0)
    v = np.clip(p0[..., 1], 1.0, H - 2.0)
    lam = np.full(u.shape, float(cfg.lambda_init))
    converged = np.zeros(u.shape, dtype=bool)
    S = bilinear_sample(RG, u, v)  # (B, N, 9); re-used while a step is accepted
    for _ in range(cfg.max_iter):
        cost, e = _ray_cost(S, t)
        gx, gy = S[..., 3:6], S[..., 6:9]
        A00 = _dot3(gx, gx) + lam
        A01 = _dot3(gx, gy)
        A11 = _dot3(gy, gy) + lam
        b0, b1 = -_dot3(e, gx), -_dot3(e, gy)
        det = A00 * A11 - A01 * A01
        ok = det > DET_MIN
        det = np.where(ok, det, 1.0)
        du = np.where(ok, (A11 * b0 - A01 * b1) / det, 0.0)
        dv = np.where(ok, (A00 * b1 - A01 * b0) / det, 0.0)
        u_new = np.clip(u + du, 1.0, W - 2.0)
        v_new = np.clip(v + dv, 1.0, H - 2.0)
        S_new = bilinear_sample(RG, u_new, v_new)
        new_cost, _ = _ray_cost(S_new, t)
        acc = (new_cost < cost) & has_ray
        u, v = np.where(acc, u_new, u), np.where(acc, v_new, v)
        S = np.where(acc[..., None], S_new, S)
        lam = np.where(acc, lam * 0.1, lam * 10.0)
        converged = (np.where(acc, new_cost, cost) < cfg.convergence_thresh) & has_ray
    p = np.stack([u, v], axis=-1)
    return (p, converged) if batched else (p[0], converged[0])


# --- §4.4 descriptor refinement ----------------------------------------------------------------


def refine_matches(D11: Any, D21: Any, p1: Any, cfg: MatchingConfig = MatchingConfig()) -> IntArray:
    """Coarse-to-fine search for the best descriptor similarity around each integer match.

    Paper: §3.2 (feature refinement). Upstream: matching_kernels.cu::refine_matches_kernel.

        (u0, v0) = p1[n];  best = 0.0  (REFINE_BEST_INIT)
        for d = dilation_max, ..., 1:            rd = radius · d
            for i = 0, d, ..., 2 rd  (u offset, outer);  for j = 0, d, ..., 2 rd  (v offset):
                (u, v) = (u0 − rd + i, v0 − rd + j), skipped unless inside [0, W) x [0, H)
                score = D21[n] · D11[v, u];  if score > best: best = score, p* = (u, v)
            (u0, v0) = p*                          # next level centred on the best so far

    ``best`` is never reset, so the score of the returned pixel never decreases; a pixel with
    no positive-score candidate keeps its match. Upstream accumulates in fp16; here float64.

    Args:
        D11: (H, W, F) or (B, H, W, F) descriptors of image 1 (finite).
        D21: (N, F) or (B, N, F) descriptors of image 2 (finite).
        p1: (N, 2) or (B, N, 2) integer (u, v) inside the image.
        cfg: uses ``radius`` and ``dilation_max``.

    Returns:
        (N, 2) or (B, N, 2) int64 refined (u, v).
    """
    D1, batched = image_batch(D11, "D11", None)
    D1 = as_float_array(D1, "D11")
    B, H, W, F = D1.shape
    lead = (B,) if batched else ()
    D2 = as_float_array(D21, "D21")
    if D2.ndim != len(lead) + 2 or D2.shape[:-2] != lead or D2.shape[-1] != F:
        raise ValueError(f"D21: expected shape (N, {F}) or (B, N, {F}), got {D2.shape}")
    N = D2.shape[-2]
    p = int_pixels(p1, "p1", (*D2.shape[:-1], 2), H, W).reshape(B, N, 2)
    D2 = D2.reshape(B, N, F)
    flat = D1.reshape(B, H * W, F)
    b = np.arange(B)[:, None]
    u0, v0 = p[..., 0], p[..., 1]
    u_best, v_best = u0.copy(), v0.copy()
    best = np.full(u0.shape, REFINE_BEST_INIT)
    for d in range(cfg.dilation_max, 0, -1):
        rd = cfg.radius * d
        for i in range(0, 2 * rd + 1, d):
            for j in range(0, 2 * rd + 1, d):
                u, v = u0 - rd + i, v0 - rd + j
                inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
                lin = np.where(inside, u + W * v, 0)
                score = np.einsum("bnf,bnf->bn", D2, flat[b, lin])
                better = inside & (score > best)
                best = np.where(better, score, best)
                u_best, v_best = np.where(better, u, u_best), np.where(better, v, v_best)
        u0, v0 = u_best, v_best
    out = np.stack([u_best, v_best], axis=-1)
    return out if batched else out[0]


# --- §4.3 + §4.5 the entry point -----------------------------------------------------------------


def _initial_pixels(idx_init: IntArray | None, B: int, H: int, W: int) -> FloatArray:
    """(B, N, 2) float (u, v) start of the LM: the identity grid, or ``(idx % W, idx // W)``."""
    if idx_init is None:
        idx_init = np.broadcast_to(np.arange(H * W, dtype=np.int64), (B, H * W))
    return np.stack([idx_init % W, idx_init // W], axis=-1).astype(np.float64)


def match(
    X11: FloatArray,
    X21: FloatArray,
    D11: FloatArray,
    D21: FloatArray,
    idx_init: IntArray | None = None,
    cfg: MatchingConfig = MatchingConfig(),
) -> tuple[IntArray, BoolArray]:
    """Match every pixel of image 2 to a pixel of image 1 (iterative projection + refinement).

    Paper: §3.2. Upstream: matching.py::match / match_iterative_proj.

        p*    = iter_proj(ray image of X11, X21, p_init)        (float, clamped)
        p1    = ⌊p*⌋                                              (truncation, p* >= 1)
        valid = converged ∧ ‖X11[p1] − X21[n]‖ < dist_thresh      (before refinement)
        p1    = refine_matches(D11, D21, p1)  if radius > 0 and X21[n] ≠ 0
        idx   = u + W v

    Args:
        X11: (H, W, 3) or (B, H, W, 3) pointmap of image 1 in camera 1.
        X21: same shape, pointmap of image 2 in camera 1.
        D11, D21: (H, W, F) or (B, H, W, F) unit descriptors of images 1 and 2 (finite).
        idx_init: None (identity start) or (N,) / (B, N) integer linear indices into image 1.
        cfg: :class:`MatchingConfig`.

    Returns:
        idx_1_to_2: (N,) or (B, N) int64, for every pixel n of image 2 the linear index
            ``u + W v`` of its match in image 1.
        valid: (N,) or (B, N) bool. Zero or non-finite points (own or matched) are invalid.
            A pixel n whose own point ``X21[n]`` is zero or non-finite is not matched at all:
            its LM keeps the start and the refinement skips it (``idx`` is the start pixel,
            clamped to the image interior), so zeroing the points of the pixels one does not
            need is how a caller matches a subset (``mslam``'s pixel grids).
    """
    X1, X2, D1, D2, idx0, batched = check_match_inputs(X11, X21, D11, D21, idx_init)
    X1, X2 = _points(X1, "X11"), _points(X2, "X21")
    D1, D2 = as_float_array(D1, "D11"), as_float_array(D2, "D21")
    B, H, W, F = D1.shape
    N = H * W
    X2f, X1f = X2.reshape(B, N, 3), X1.reshape(B, N, 3)
    p, converged = iter_proj(ray_image_and_gradients(X1), X2f, _initial_pixels(idx0, B, H, W), cfg)
    p1 = p.astype(np.int64)  # truncation == floor because p >= 1
    lin = p1[..., 0] + W * p1[..., 1]
    X1_at = X1f[np.arange(B)[:, None], lin]
    diff = X1_at - X2f
    dist_ok = np.sqrt(_dot3(diff, diff)) < cfg.dist_thresh
    own_ok = _point_ok(X2f)
    valid = converged & dist_ok & own_ok & _point_ok(X1_at)
    if cfg.radius > 0:
        # A pixel without a point is not refined: it keeps the truncated start, so a caller
        # that zeroes the points it does not need (a pixel grid) pays for those only.
        p1 = np.where(own_ok[..., None], refine_matches(D1, D2.reshape(B, N, F), p1, cfg), p1)
    idx = p1[..., 0] + W * p1[..., 1]
    return (idx, valid) if batched else (idx[0], valid[0])
