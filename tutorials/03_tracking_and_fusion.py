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
# # 03 — Tracking and fusion (paper §3.3, Eq. 4–8; §3.7)
#
# MASt3R-SLAM tracks each frame against the last keyframe by estimating the relative
# similarity `T_CkCf` that moves the frame's points `X_f` onto the keyframe's canonical
# points `X_k`. Without calibration the error is a **ray** error (direction, 3 rows) plus a
# very lightly weighted **distance** error (1 row); with known intrinsics it is a **pixel**
# plus **log-depth** error. IRLS with a per-component Huber weight makes it robust to bad
# matches. After tracking, the keyframe's pointmap is **fused** with the new prediction.
#
# This tutorial uses the reference implementation (`mslam_ref`); `mslam_fast` has the same
# functions.
#
# **What you will learn**
#
# 1. the ray error of paper Eq. 6 (plus its small distance term), computed from scratch and
#    checked against the library;
# 2. how the per-match weight of Eq. 5, `w(q, σ²) = σ²/q`, becomes `√q/σ` on the residual and
#    `q/σ²` in `JᵀWJ` (Eq. 7), and what Huber does on top;
# 3. the cost landscape the Gauss–Newton of Eq. 7 descends, over translation and scale;
# 4. calibrated tracking (§3.7);
# 5. fusion (Eq. 8): the keyframe's canonical pointmap absorbs `T_kf · X^k_f` — the network's
#    prediction of the *keyframe's* points in the pair with frame f, moved into camera k — with
#    its confidence `C^k_f`; before/after clouds and the alternatives of Table 5;
# 6. the Taichi twin against the reference (result and time).

# %%
import matplotlib.pyplot as plt
import numpy as np

from mslam.datasets.synthetic import make_sequence
from mslam_ref import fusion, sim3, tracking
from mslam_ref.pointmap import backproject

seq = make_sequence("loop", n_frames=60, width=96, height=72, seed=0)
K, H, W = seq.K, seq.height, seq.width
kf, fr = seq[0], seq[2]
X_k = backproject(kf.depth, K)  # keyframe canonical pointmap (camera k)
X_fr = backproject(fr.depth, K)  # frame pointmap (camera f)
T_true = sim3.mul(sim3.inv(kf.T_WC), fr.T_WC)  # T_CkCf

# %% [markdown]
# ## Correspondences
# Matching (tutorial 02) gives, for every keyframe pixel n, a frame pixel `idx_f2k[n]`. Here we
# compute it exactly by projecting the keyframe's points into the frame, and we corrupt 5 % of
# the matches to see the robust weights at work.

# %%
P = sim3.act(sim3.inv(T_true), X_k.reshape(-1, 3))  # keyframe points seen from the frame
u = np.rint(K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2]).astype(int)
v = np.rint(K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]).astype(int)
valid = (u >= 0) & (u < W) & (v >= 0) & (v < H)
idx_f2k = np.where(valid, u + W * v, 0)
rng = np.random.default_rng(0)
bad = rng.random(H * W) < 0.05
idx_f2k[bad] = rng.integers(0, H * W, bad.sum())
X_f = X_fr.reshape(-1, 3)[idx_f2k]
# Match quality (paper Eq. 5's q): q_n = sqrt(Q_f[idx_f2k[n]] · Q_k[n]) from the two descriptor
# confidences of the pair; both are 2 here, so q = 2 on every pixel.
Q = tracking.match_quality(np.full(H * W, 2.0), np.full(H * W, 2.0), idx_f2k)
assert np.allclose(Q, 2.0)
print(f"valid matches: {valid.mean():.0%}, corrupted: {bad.mean():.0%}")
assert valid.mean() > 0.5

# %% [markdown]
# ## The ray and distance residuals
# `r_n = [psi(Xk_n) - psi(T Xf_n), |Xk_n| - |T Xf_n|]`, shown at a perturbed pose. The ray
# error is an angle (radians); the distance error is in metres and is weighted 1/10 against
# the ray's 1/0.003 — a ratio of about 1e-7 in information.

# %%
T_init = sim3.retract(T_true, np.array([0.03, -0.02, 0.02, 0.01, 0.02, -0.01, 0.02]))
r, J = tracking.ray_dist_residual_and_jacobian(T_init, X_f, X_k)
fig, ax = plt.subplots(1, 2, figsize=(9, 3))
ray_err = np.where(valid, np.linalg.norm(r[:, :3], axis=1), np.nan).reshape(H, W)
ax[0].imshow(ray_err, vmax=np.nanpercentile(ray_err, 95))
ax[0].set_title("|ray residual| (rad)")
ax[1].imshow(np.where(valid, r[:, 3], np.nan).reshape(H, W), cmap="coolwarm")
ax[1].set_title("distance residual (m)")
plt.show()
assert r.shape == (H * W, 4) and J.shape == (H * W, 4, 7)

# From scratch (Eq. 6): r = [ψ(X_k) − ψ(T X_f), ‖X_k‖ − ‖T X_f‖].
P_mine = sim3.act(T_init, X_f)
psi = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)
r_mine = np.concatenate(
    [psi(X_k.reshape(-1, 3)) - psi(P_mine), (np.linalg.norm(X_k.reshape(-1, 3), axis=-1) - np.linalg.norm(P_mine, axis=-1))[:, None]],
    axis=1,
)  # fmt: skip
assert np.allclose(r_mine, r, atol=1e-12)

# %% [markdown]
# ## IRLS weights
# Each whitened residual component gets the Huber weight `min(1, 1.345/|w r|)`. The corrupted
# matches get small weights. Good pixels do not all keep weight 1, even at the solution: the
# "exact" matches here are rounded to the nearest pixel, so their ray error is up to half a
# pixel (about 0.5/f rad), several σ_ray = 0.003 rad, and Huber down-weights them (the mean
# printed below is about 0.77). The corrupted ones fall far lower.

# %%
cfg = tracking.TrackingConfig()
from mslam_ref.robust import huber_weight

sqrt_info = (np.sqrt(Q) * valid)[:, None] / np.array([cfg.sigma_ray] * 3 + [cfg.sigma_dist])
T_est, info = tracking.solve(X_f, X_k, Q, valid, T_init, cfg)
r_final, _ = tracking.ray_dist_residual_and_jacobian(T_est, X_f, X_k)
w = huber_weight(sqrt_info * r_final)[:, :3].min(axis=1)
fig, ax = plt.subplots(figsize=(4, 3))
ax.imshow(np.where(valid, w, np.nan).reshape(H, W), vmin=0, vmax=1)
ax.set_title("smallest ray weight per pixel")
plt.show()
print(f"mean weight: corrupted {w[bad & valid].mean():.3f}, good {w[~bad & valid].mean():.3f}")
assert w[bad & valid].mean() < 0.5 * w[~bad & valid].mean()

# %% [markdown]
# ## The cost landscape
# The robust cost of Eq. 6 around the solution, over the x-translation and the log-scale of
# `T_CkCf` (a 2-D slice of the 7-D problem). Along x it is a smooth, steep bowl — which is why a
# handful of Gauss–Newton steps suffice. Along the scale it is almost flat: scaling the frame's
# points about its own camera centre leaves their *directions* unchanged, so the ray error only
# sees the scale through the small translation between the cameras, and through the distance
# term, whose weight is about 1e-7 of the rays'. Scale is the weakly observed direction of
# tracking; the backend and fusion average it out over many frames.

# %%
grid = np.linspace(-0.1, 0.1, 21)
landscape = np.zeros((len(grid), len(grid)))
for a_, dx in enumerate(grid):
    for b_, ds in enumerate(grid):
        T_probe = sim3.retract(T_est, np.array([dx, 0, 0, 0, 0, 0, ds]))
        landscape[b_, a_] = tracking.linearize(T_probe, X_f, X_k, Q, valid, cfg)[2]
fig, ax = plt.subplots(figsize=(4.5, 3.6))
cs = ax.contourf(grid, grid, np.log10(landscape), 20)
plt.colorbar(cs, ax=ax, label="log10 robust cost")
ax.plot(0, 0, "r+", ms=12)
ax.set_xlabel("x-translation perturbation (m)")
ax.set_ylabel("log-scale perturbation")
ax.set_title("tracking cost around the solution")
plt.show()
assert landscape[10, 10] == landscape.min()

# %% [markdown]
# ## The pose converging
# The cost is evaluated before each update; tracking stops when it changes by less than
# 0.1 % or the step is shorter than 1e-3.

# %%
err = sim3.log(sim3.mul(T_est, sim3.inv(T_true)))
print(info)
print(
    f"rotation error {np.linalg.norm(err[3:6]):.2e} rad, translation error "
    f"{np.linalg.norm(T_est[:3] - T_true[:3]):.2e} m, scale {T_est[7]:.4f}"
)
fig, ax = plt.subplots(figsize=(4, 3))
ax.semilogy(info.costs, "o-")
ax.set_xlabel("iteration")
ax.set_ylabel("robust cost")
plt.show()
assert info.converged and not info.failed and np.linalg.norm(err[3:6]) < 5e-3

# After tracking, the new-keyframe test (§3.4, threshold ω_k = 0.333): frame 2 still shares
# most of the keyframe's view, so no new keyframe yet.
new_kf = tracking.needs_new_keyframe(idx_f2k, valid, valid & (Q > cfg.Q_conf), cfg)
print("new keyframe needed:", new_kf)
assert not new_kf

# %% [markdown]
# ## Calibrated tracking
# With K, both pointmaps are first put on their known rays (only depth survives) and the
# error becomes pixel + log-depth.

# %%
from mslam_ref.calib import constrain_points_to_ray

X_k_c = constrain_points_to_ray(X_k, K)
X_f_c = constrain_points_to_ray(X_fr, K).reshape(-1, 3)[idx_f2k]
T_cal, info_c = tracking.solve(X_f_c, X_k_c, Q, valid, T_init, cfg, K)
err_c = sim3.log(sim3.mul(T_cal, sim3.inv(T_true)))
print(
    f"calibrated: {info_c.iterations} iterations, rotation error {np.linalg.norm(err_c[3:6]):.2e}"
)
assert np.linalg.norm(err_c[3:6]) < 5e-3

# %% [markdown]
# ## Fusion modes compared
# Ten noisy predictions of the keyframe pointmap, with confidences that track the noise, are
# fused with each mode. The weighted average (the default) reduces the error most;
# `weighted_spherical` averages azimuths without wrapping at ±π (as upstream), which breaks
# points near the x-z half-plane x < 0.

# %%
X_true = X_k.reshape(-1, 3)
results = {}
for mode in fusion.FILTERING_MODES:
    fcfg = fusion.FusionConfig(mode)
    r2 = np.random.default_rng(1)
    state = None
    for _ in range(10):
        sigma = r2.uniform(0.005, 0.05, H * W)
        Xn = X_true + r2.normal(0, 1, X_true.shape) * sigma[:, None]
        Cn = 1.0 + 0.05 / sigma
        state = (
            fusion.init_pointmap(Xn, Cn, fcfg)
            if state is None
            else fusion.update_pointmap(state, Xn, Cn, fcfg)
        )
    results[mode] = float(np.sqrt(np.mean(np.sum((state.X_canon - X_true) ** 2, axis=1))))
for mode, e in results.items():
    print(f"{mode:20s} RMS error {e * 1000:.1f} mm")
fig, ax = plt.subplots(figsize=(6, 3))
ax.bar(list(results), [1000 * e for e in results.values()])
ax.set_ylabel("RMS error (mm)")
ax.tick_params(axis="x", rotation=30)
plt.show()
assert results["weighted_pointmap"] == min(results.values())
assert results["weighted_pointmap"] < 0.5 * results["recent"]

# %% [markdown]
# ## Before and after fusion
# The same ten predictions, one slice of the point cloud (the row through the image centre),
# seen from above: one prediction alone (grey) against the weighted average (blue) and the
# truth (black).

# %%
fcfg = fusion.FusionConfig("weighted_pointmap")
r2 = np.random.default_rng(1)
state, first = None, None
for _ in range(10):
    sigma = r2.uniform(0.005, 0.05, H * W)
    Xn = X_true + r2.normal(0, 1, X_true.shape) * sigma[:, None]
    Cn = 1.0 + 0.05 / sigma
    first = Xn if first is None else first
    state = (
        fusion.init_pointmap(Xn, Cn, fcfg)
        if state is None
        else fusion.update_pointmap(state, Xn, Cn, fcfg)
    )
row = slice((H // 2) * W, (H // 2 + 1) * W)
fig, ax = plt.subplots(figsize=(6, 3))
ax.plot(first[row, 0], first[row, 2], ".", color="0.6", label="one prediction")
ax.plot(state.X_canon[row, 0], state.X_canon[row, 2], ".", color="C0", label="fused (10)")
ax.plot(X_true[row, 0], X_true[row, 2], "k-", lw=1, label="truth")
ax.set_xlabel("x (m)")
ax.set_ylabel("z (m)")
ax.legend()
plt.show()
assert np.abs(state.X_canon - X_true).mean() < 0.5 * np.abs(first - X_true).mean()

# %% [markdown]
# ## Reference against fast
# `mslam_fast.tracking.solve` runs the same Gauss–Newton driver with a Taichi linearisation
# (one kernel: residual, Jacobian, weights and the 7×7 reduction per pixel).

# %%
import time

import mslam_fast
from mslam_fast import tracking as fast_tracking

mslam_fast.init("cpu", "f64")
fast_tracking.solve(X_f, X_k, Q, valid, T_init, cfg)  # compile
t0 = time.perf_counter()
T_ref, _ = tracking.solve(X_f, X_k, Q, valid, T_init, cfg)
t1 = time.perf_counter()
T_fast, _ = fast_tracking.solve(X_f, X_k, Q, valid, T_init, cfg)
t2 = time.perf_counter()
print(f"reference {1e3 * (t1 - t0):.1f} ms, fast {1e3 * (t2 - t1):.1f} ms; "
      f"max |T_ref - T_fast| = {np.abs(T_ref - T_fast).max():.1e}")  # fmt: skip
np.testing.assert_allclose(T_fast, T_ref, atol=1e-9)

# %% [markdown]
# ## Exercises
#
# 1. A ray component of a match with confidence `q = 2` (as here): what is its weight in
#    `JᵀWJ` before Huber? Store it in `ex1` (use `cfg.sigma_ray`).
# 2. How much less information does a distance row carry than a ray row (same q)? Store the
#    ratio in `ex2`.
# 3. Fuse two predictions of one point by hand with Eq. 8: `x1 = 1.0` with `C1 = 3` and
#    `x2 = 2.0` with `C2 = 1`. Store the fused value and confidence as `ex3 = (x, C)`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution
ex1 = 2.0 / cfg.sigma_ray**2
ex2 = (1 / cfg.sigma_dist**2) / (1 / cfg.sigma_ray**2)
ex3 = ((3 * 1.0 + 1 * 2.0) / (3 + 1), 3 + 1)

# %%
# Check
i_good = int(np.flatnonzero(valid)[0])
assert np.isclose(ex1, sqrt_info[i_good, 0] ** 2)
assert np.isclose(ex2, (sqrt_info[i_good, 3] / sqrt_info[i_good, 0]) ** 2)
st = fusion.update_pointmap(
    fusion.init_pointmap(np.array([[1.0, 0, 1]]), np.array([3.0]), fcfg),
    np.array([[2.0, 0, 1]]), np.array([1.0]), fcfg,
)  # fmt: skip
assert np.isclose(st.X_canon[0, 0], ex3[0]) and np.isclose(st.C[0], ex3[1])
print("exercises: all correct")
