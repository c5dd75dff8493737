# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 02 — Pointmap matching: iterative projection and descriptor refinement
#
# MASt3R-SLAM (arXiv:2412.12392, §3.2) needs, for every pixel of a new frame, the pixel of
# the keyframe that sees the same 3-D point. MASt3R predicts both pointmaps in the keyframe's
# camera (camera 1): `X11` for image 1 and `X21` for image 2. So the match of pixel n of
# image 2 is the pixel p of image 1 whose **ray** points the same way:
#
# $$p^*(n) = \arg\min_p \big\| \psi(X_{11}(p)) - \psi(X_{21}[n]) \big\|^2, \qquad
#   \psi(x) = x / \|x\|.$$
#
# Instead of a nearest-neighbour search over all rays, each pixel runs ten
# Levenberg–Marquardt steps on its position (u, v) in the *ray image* of camera 1, then
# takes a 3-D distance (occlusion) test, then refines the integer match by a coarse-to-fine
# search for the best descriptor similarity.
#
# **What you will learn:** paper Eq. 2–3 (the ray error is an angle), the ray image and its gradients, one pixel's LM path, a match-quality
# image against ground truth, what refinement changes, and the NumPy reference beside the
# Taichi kernel. **Prerequisites:** tutorials 00 (Sim(3)) and 01 (pointmaps and priors).

# %%
import time

import matplotlib.pyplot as plt
import numpy as np

from mslam.datasets.synthetic import make_sequence
from mslam.priors.descriptors import patch_descriptors
from mslam_ref import matching, sim3
from mslam_ref.pointmap import backproject, project

np.set_printoptions(precision=4, suppress=True)

# %% [markdown]
# ## 1. A pair with known correspondence
#
# Two frames of the synthetic room, with exact depth and poses: `X11` is frame 0 back-projected
# in camera 1, `X21` is frame 2's points moved into camera 1 by the true relative pose
# $T_{12} = T_{W1}^{-1} T_{W2}$. Projecting `X21` with K gives the true match of every pixel;
# comparing depths tells which ones camera 1 actually sees. Descriptors are the 24-D patch
# descriptors the synthetic prior uses in place of MASt3R's feature head.

# %%
W, H = 128, 96
seq = make_sequence("loop", n_frames=40, width=W, height=H, seed=0)
f1, f2 = seq[0], seq[2]
X11 = backproject(f1.depth, seq.K)
X21 = sim3.act(sim3.mul(sim3.inv(f1.T_WC), f2.T_WC), backproject(f2.depth, seq.K))
D11, D21 = patch_descriptors(f1.rgb)[0], patch_descriptors(f2.rgb)[0]

uv_true, z = project(X21.reshape(-1, 3), seq.K)
inside = (z > 0) & np.all((uv_true >= 0) & (uv_true <= [W - 1, H - 1]), axis=-1)
ui, vi = np.clip(np.round(uv_true).astype(int), 0, [W - 1, H - 1]).T
visible = inside & (np.abs(f1.depth[vi, ui] - z) < 0.03 * z + 0.01)
print(f"{visible.mean():.1%} of the pixels of image 2 are visible in image 1")

# %% [markdown]
# ## 2. The ray image and its gradients
#
# The LM samples a 9-channel image of camera 1: the unit rays $R = \psi(X_{11})$ and their
# Scharr derivatives along u and v (reflect padding, kernels scaled by 1/32 so that a linear
# ramp of slope a has derivative exactly a). Every pixel's ray is unit length; the gradients are
# about 1/f per pixel.

# %%
RG = matching.ray_image_and_gradients(X11)
R, gx, gy = RG[..., :3], RG[..., 3:6], RG[..., 6:9]

fig, ax = plt.subplots(1, 3, figsize=(11, 2.8))
ax[0].imshow(0.5 + 0.5 * R)
ax[0].set_title("rays ψ(X11) as RGB")
ax[1].imshow(np.linalg.norm(gx, axis=-1))
ax[1].set_title("‖∂R/∂u‖")
ax[2].imshow(np.linalg.norm(gy, axis=-1))
ax[2].set_title("‖∂R/∂v‖")
for a in ax:
    a.axis("off")
plt.show()

# %%
# Checkpoint: unit rays; on a linear ramp the Scharr derivative is the slope.
assert np.allclose(np.linalg.norm(R, axis=-1), 1.0)
f = seq.K[0, 0]
assert np.allclose(np.median(np.linalg.norm(gx, axis=-1)), 1 / f, rtol=0.2)
ramp = (0.3 * np.arange(8.0)[None, :] + 0.0 * np.arange(6.0)[:, None])[..., None]
assert np.allclose(matching.scharr_gradients(ramp)[0][1:-1, 1:-1], 0.3)

# %% [markdown]
# ## 3. One pixel's Levenberg–Marquardt path
#
# For a target ray $t = \psi(X_{21}[n])$ and a position p = (u, v), the residual is
# $e = \hat r(p) - t$ with $\hat r$ the *re-normalised* bilinear sample of R. The Jacobian used
# is the bilinear sample of the gradient image, $J = [g_x\ g_y]$ (3x2), **without** the
# derivative of the re-normalisation — upstream's choice; see `docs/matching.md` for why it
# still converges. The step solves
#
# $$(J^\top J + \lambda I)\,\delta = -J^\top e$$
#
# in closed form, clamps p to $[1, W-2]\times[1, H-2]$, and is accepted only if the cost drops
# (then $\lambda \leftarrow \lambda/10$, else $\lambda \leftarrow 10\lambda$). All ten iterations
# always run. Because there is no early exit, running `iter_proj` with `max_iter = k` gives the
# state after k iterations, which is how we draw the path.

# %%
n = int(np.flatnonzero(visible & (np.abs(uv_true[:, 0] - np.arange(H * W) % W) > 4))[40])
start = np.array([[n % W, n // W]], dtype=float)  # the identity guess
path, costs = [], []
for k in range(11):
    p, conv = matching.iter_proj(
        RG, X21.reshape(-1, 3)[n : n + 1], start, matching.MatchingConfig(max_iter=k)
    )
    path.append(p[0])
    r = matching.bilinear_sample(RG, p[:, 0], p[:, 1])[0, :3]
    costs.append(np.sum((r / np.linalg.norm(r) - matching.normalize(X21.reshape(-1, 3)[n])) ** 2))
path = np.array(path)
print("start", path[0], "-> end", path[-1], " truth", uv_true[n], " converged", conv[0])

fig, ax = plt.subplots(1, 2, figsize=(10, 3))
ax[0].imshow(0.5 + 0.5 * R)
ax[0].plot(path[:, 0], path[:, 1], "w.-")
ax[0].plot(*uv_true[n], "rx", ms=10)
ax[0].set_title(f"LM path of pixel n = {n} on the ray image")
ax[1].semilogy(costs, "o-")
ax[1].axhline(matching.MatchingConfig().convergence_thresh, ls="--", c="k")
ax[1].set_xlabel("iteration")
ax[1].set_ylabel("‖ψ − t‖²")
plt.show()

# %% [markdown]
# **From scratch.** Three LM iterations of that pixel in a few lines of NumPy, compared with the
# library (the same bilinear samples, the same 2×2 solve, the same accept/reject rule).

# %%
t_ray = matching.normalize(X21.reshape(-1, 3)[n])
p_mine, lam = np.clip(start[0], 1.0, [W - 2.0, H - 2.0]), matching.MatchingConfig().lambda_init


def ray_cost(p):
    S = matching.bilinear_sample(RG, p[None, 0], p[None, 1])[0]
    e = S[:3] / np.linalg.norm(S[:3]) - t_ray
    return e @ e, e, np.stack([S[3:6], S[6:9]], axis=1)  # cost, e, J (3x2)


for _ in range(3):
    c, e, J = ray_cost(p_mine)
    step = np.linalg.solve(J.T @ J + lam * np.eye(2), -J.T @ e)
    p_try = np.clip(p_mine + step, 1.0, [W - 2.0, H - 2.0])
    if ray_cost(p_try)[0] < c:
        p_mine, lam = p_try, lam / 10
    else:
        lam *= 10
p_lib, _ = matching.iter_proj(
    RG, X21.reshape(-1, 3)[n : n + 1], start, matching.MatchingConfig(max_iter=3)
)
print("from scratch", p_mine, " library", p_lib[0])
assert np.allclose(p_mine, p_lib[0], atol=1e-9)

# %%
# Checkpoint: accepted steps only, so the cost never rises; it ends below the threshold
# (about 1e-3 rad) and near the true sub-pixel position.
assert np.all(np.diff(costs) <= 0)
assert conv[0] and costs[-1] < 1e-6
assert np.abs(path[-1] - uv_true[n]).max() < 0.5

# %% [markdown]
# ## 4. All pixels: match quality against ground truth
#
# `match` runs the LM for every pixel of image 2, **truncates** the sub-pixel result to integer
# pixels (not rounding: a result at u = 10.7 becomes 10), and keeps a match only if it converged
# and the 3-D points agree: $\|X_{11}[p] - X_{21}[n]\| < 0.1$. With `radius=0` the descriptor
# refinement is off.

# %%
t0 = time.perf_counter()
idx0, valid0 = matching.match(X11, X21, D11, D21, cfg=matching.MatchingConfig(radius=0))
t_proj = time.perf_counter() - t0


def pixel_error(idx):
    return np.maximum(np.abs(idx % W - uv_true[:, 0]), np.abs(idx // W - uv_true[:, 1]))


err0 = pixel_error(idx0)
ok = valid0 & visible
print(
    f"valid: {valid0[visible].mean():.1%} of visible pixels, {(valid0 & ~visible).sum()} "
    f"valid but occluded; within 1 px: {np.mean(err0[ok] < 1):.1%}  ({1e3 * t_proj:.0f} ms)"
)

fig, ax = plt.subplots(1, 2, figsize=(10, 3))
im = ax[0].imshow(np.where(ok, err0, np.nan).reshape(H, W), vmin=0, vmax=2, cmap="viridis")
ax[0].set_title("|error| (px) of valid matches, no refinement")
plt.colorbar(im, ax=ax[0])
ax[1].imshow((valid0.astype(int) + visible).reshape(H, W), cmap="gray")
ax[1].set_title("white: valid & visible, grey: visible only")
plt.show()

# %%
# Checkpoint: nearly all valid visible pixels within one pixel of the truth; the occlusion
# test rejects what camera 1 cannot see.
assert np.mean(err0[ok] < 1.0) >= 0.95
assert valid0[visible].mean() >= 0.9
assert (valid0 & ~visible).sum() <= 0.02 * valid0.sum()

# %% [markdown]
# ## 5. Descriptor refinement
#
# Around each integer match, a 7x7 grid with dilation d = 5, 4, 3, 2, 1 is searched for the
# largest descriptor similarity $D_{21}[n] \cdot D_{11}[p]$; each level is centred on the best
# so far and the best score is **never reset**, so it can only rise (it starts at 0, so only
# positive similarities move a match). Validity is not recomputed. The window reaches ±45 px:
# with MASt3R's descriptors this pulls matches onto the right pixel; with the stand-in patch
# descriptors used here the median error drops, but some matches jump to look-alike pixels.

# %%
t0 = time.perf_counter()
idx1, valid1 = matching.match(X11, X21, D11, D21)
t_full = time.perf_counter() - t0
err1 = pixel_error(idx1)


def score(idx):
    return np.einsum("nf,nf->n", D21.reshape(-1, 24), D11.reshape(-1, 24)[idx])


print(
    f"median error {np.median(err0[ok]):.2f} px -> {np.median(err1[ok]):.2f} px; "
    f"within 1 px {np.mean(err0[ok] < 1):.1%} -> {np.mean(err1[ok] < 1):.1%} "
    f"({1e3 * t_full:.0f} ms with refinement)"
)

fig, ax = plt.subplots(1, 2, figsize=(10, 3))
ax[0].hist([err0[ok], np.minimum(err1[ok], 5)], bins=30, label=["projection", "+ refinement"])
ax[0].legend()
ax[0].set_xlabel("error (px, clipped at 5)")
ax[1].imshow(np.where(ok, err1, np.nan).reshape(H, W), vmin=0, vmax=2)
ax[1].set_title("|error| after refinement")
plt.show()

# %%
# Checkpoint: same validity, score never lower, median error smaller.
assert np.array_equal(valid1, valid0)
assert np.all(score(idx1) >= score(idx0) - 1e-12)
assert np.median(err1[ok]) < np.median(err0[ok])

# %% [markdown]
# ## 6. Reference and fast, side by side
#
# `mslam_fast.matching.match` has the same signature; one Taichi thread per target pixel runs
# the LM, the truncation, the distance test and the refinement in one kernel. At float64 it
# returns the same integer matches up to last-bit effects (a result within 1e-15 px of an
# integer, or two exactly tied descriptor scores).

# %%
try:
    import mslam_fast
    from mslam_fast import matching as fast_matching

    mslam_fast.init("cpu", "f64")
except Exception as exc:  # Taichi cannot initialise here
    fast_matching = None
    print(f"skipping the fast half: {exc}")

if fast_matching is not None:
    fast_matching.match(X11, X21, D11, D21)  # compile once
    t0 = time.perf_counter()
    idx_f, valid_f = fast_matching.match(X11, X21, D11, D21)
    t_fast = time.perf_counter() - t0
    same = np.mean((idx_f == idx1) & (valid_f == valid1))
    print(f"reference {1e3 * t_full:.0f} ms, fast {1e3 * t_fast:.1f} ms; identical on {same:.2%}")
    fig, ax = plt.subplots(1, 2, figsize=(10, 3))
    ax[0].imshow(np.where(valid1, err1, np.nan).reshape(H, W), vmin=0, vmax=2)
    ax[0].set_title("reference: |error|")
    ax[1].imshow(np.where(valid_f, pixel_error(idx_f), np.nan).reshape(H, W), vmin=0, vmax=2)
    ax[1].set_title("fast (Taichi): |error|")
    plt.show()
    # Checkpoint: the two implementations agree.
    assert same >= 0.999

# %% [markdown]
# ## Exercises
#
# 1. Paper Eq. 3 says `‖ψ1 − ψ2‖² = 2(1 − cos θ)`. Convert the final LM cost of the pixel of
#    section 3 into the angle θ between the two rays, in degrees; store it in `ex1`.
# 2. Which fraction of the valid matches does descriptor refinement move (a different integer
#    pixel than without refinement)? Store it in `ex2`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution
# 2(1 - cos θ) = 4 sin²(θ/2); arcsin keeps tiny angles accurate where arccos(1 - x) rounds to 0
ex1 = float(np.degrees(2.0 * np.arcsin(np.sqrt(costs[-1]) / 2.0)))
ex2 = float(np.mean(idx1[valid0 & valid1] != idx0[valid0 & valid1]))
print(
    f"final angle {ex1:.2e} deg ({3600 * ex1:.3f} arcsec); refinement moves {ex2:.1%} of the valid matches"
)

# %%
# Check
r_end = matching.normalize(matching.bilinear_sample(RG, path[-1:, 0], path[-1:, 1])[0, :3])
theta = np.arctan2(np.linalg.norm(np.cross(r_end, t_ray)), r_end @ t_ray)  # stable angle
assert np.isclose(np.radians(ex1), theta, rtol=1e-6, atol=1e-12)
assert 0.0 < ex2 < 1.0
print("exercises: all correct")

# %% [markdown]
# ## Where this lives in the code
#
# * `reference/mslam_ref/matching.py` — `ray_image_and_gradients`, `iter_proj`,
#   `refine_matches`, `match`, `MatchingConfig` (upstream defaults).
# * `fast/mslam_fast/matching.py` and `fast/mslam_fast/_kernels/matching.py` — the Taichi twin.
# * `tests/reference/test_matching.py`, `tests/parity/test_matching.py`,
#   `benchmarks/bench_matching.py`, and the design notes in `docs/matching.md`
#   (the matching rows of docs/paper_map.md).
