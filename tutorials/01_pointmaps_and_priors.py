# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 01 — Pointmaps and where they come from
#
# MASt3R-SLAM (Murai et al., CVPR 2025, §3) never sees features or depth directly: it sees
# **pointmaps**. For an image pair (i, j), the network returns, for every pixel of *both*
# images, a 3-D point in camera i (`X_ii`, `X_ji`), a confidence `C >= 1`, a 24-D unit
# descriptor `D` and a descriptor confidence `Q > 0`.
#
# The paper's only camera assumption (§3.1) is a *central* camera: every pointmap defines its
# own camera through its rays `ψ(X) = X/‖X‖`.
#
# **What you will learn**
#
# 1. pixels, rays and back-projection (`mslam_ref.pointmap`);
# 2. a synthetic scene with exact ground truth (`mslam_ref.synthetic`);
# 3. the synthetic prior: ground truth plus a documented noise model;
# 4. the RGB-D prior on a real 7-Scenes pair (skipped without the data folder, `MSLAM_DATA`);
# 5. upstream's resize to the network resolution and the matching intrinsics.

# %%
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from mslam.datasets.images import resize_img
from mslam.datasets.synthetic import make_sequence
from mslam.priors import check_prediction
from mslam.priors.synthetic import SyntheticPrior, SyntheticPriorConfig
from mslam_ref import sim3, so3
from mslam_ref.pointmap import backproject, camera_rays, intrinsics_after_resize


def show(images, titles, name, cmap=None):
    """Plot a row of images (``name`` is the figure's label)."""
    fig, axes = plt.subplots(1, len(images), figsize=(3.2 * len(images), 2.6))
    for ax, img, title in zip(np.atleast_1d(axes), images, titles):
        ax.imshow(img, cmap=cmap)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(name, fontsize=9)
    fig.tight_layout()
    plt.show()


def to_rgb(X):
    """Map an (H, W, 3) array to [0, 1] per channel for display (robust min/max)."""
    lo, hi = np.percentile(X.reshape(-1, 3), [2, 98], axis=0)
    return np.clip((X - lo) / np.maximum(hi - lo, 1e-9), 0, 1)


def pca_rgb(D):
    """First three principal components of (H, W, F) descriptors as an RGB image."""
    flat = D.reshape(-1, D.shape[-1])
    flat = flat - flat.mean(0)
    _, _, Vt = np.linalg.svd(flat, full_matrices=False)
    return to_rgb((flat @ Vt[:3].T).reshape(*D.shape[:2], 3))


# %% [markdown]
# ## 1. A synthetic sequence with exact ground truth
#
# A procedural room (textured walls, boxes, spheres) is ray-cast at every pixel centre, so the
# depth is exact. `seq[i]` is a `Frame` with `rgb`, `depth` (z in metres) and the ground-truth
# camera-to-world pose `T_WC` as a Sim(3) 8-vector `[t, q(xyzw), s]`.

# %%
seq = make_sequence("loop", n_frames=60, width=160, height=120, seed=0)
fi, fj = seq[0], seq[3]
print(seq, "\nK =\n", seq.K.round(2))
show([fi.rgb, fi.depth, fj.rgb, fj.depth], ["rgb i", "depth i (m)", "rgb j", "depth j"], "frames")

# %% [markdown]
# ## 2. Rays and back-projection
#
# The integer pixel (u, v) is the pixel *centre*; its ray is `[(u-cx)/fx, (v-cy)/fy, 1]` and
# back-projection multiplies it by z. Under the ground-truth poses the pointmaps of two frames
# land on the same world surface.

# %%
rays = camera_rays(seq.K, 120, 160)
X_i = backproject(fi.depth, seq.K)
assert np.allclose(X_i[..., 2], fi.depth)  # checkpoint: z of the pointmap is the depth
# From scratch: X = z K^-1 [u, v, 1] on the pixel-centre grid equals the library.
vv, uu = np.mgrid[0:120, 0:160]
X_mine = fi.depth[..., None] * (np.stack([uu, vv, np.ones_like(uu)], -1) @ np.linalg.inv(seq.K).T)
assert np.allclose(X_mine, X_i, atol=1e-12)
show([to_rgb(rays), to_rgb(X_i)], ["rays (x, y, 1)", "pointmap X_ii"], "rays")

# The centre pixel of frame j, seen from camera i, lies on frame i's surface:
T_ij = sim3.mul(sim3.inv(fi.T_WC), fj.T_WC)
p = sim3.act(T_ij, backproject(fj.depth, seq.K)[60, 80])
u, v = seq.K[0, 0] * p[0] / p[2] + seq.K[0, 2], seq.K[1, 1] * p[1] / p[2] + seq.K[1, 2]
print(f"pixel (80, 60) of j -> ({u:.2f}, {v:.2f}) in i, z = {p[2]:.4f} m")

# %% [markdown]
# ## 3. The synthetic prior
#
# `SyntheticPrior.pair(i, j)` returns what MASt3R would: `X_ii`, `X_ji` in camera i, with
# depth noise growing like z², a few outliers, a per-pair scale (pointmaps are up to scale)
# and a small Sim(3) error on `X_ji`. Confidences fall where the noise is high (far away,
# depth edges, outliers, pixels of j that camera i cannot see). Descriptors are a fixed random
# projection of normalised 7x7 colour patches (`DescriptorConfig.patch = 7`).

# %%
prior = SyntheticPrior(seq, SyntheticPriorConfig(seed=0))
pred = prior.pair(fi, fj)
check_prediction(pred)  # checkpoint: C >= 1, |D| = 1, Q > 0, finite
s_pair, E = prior.pair_errors(fi, fj)
print(f"pair scale {s_pair:.4f}; Sim(3) error: t = {E[:3].round(4)}, "
      f"angle = {np.degrees(np.linalg.norm(so3.log(E[3:7]))):.3f} deg, s = {E[7]:.4f}")  # fmt: skip
rel = np.abs(pred.X_ii[..., 2] / s_pair - fi.depth) / fi.depth
print(f"median relative depth error of X_ii: {np.median(rel):.4f}")
assert np.median(rel) < 0.02  # checkpoint: noise is small on most pixels
show(
    [to_rgb(pred.X_ii), to_rgb(pred.X_ji), pred.C_ii, pred.C_ji, pred.Q_ii, pca_rgb(pred.D_ii)],
    ["X_ii", "X_ji (in cam i)", "C_ii", "C_ji", "Q_ii", "D_ii (PCA)"],
    "synthetic_prior",
)

# %% [markdown]
# Descriptors discriminate: the descriptor of a pixel of j is closest to that of its true
# correspondent in i, compared with its neighbours a few pixels away.

# %%
cov = prior.covisible(fi, fj)
Xg = sim3.act(T_ij, backproject(fj.depth, seq.K))
ug = np.round(seq.K[0, 0] * Xg[..., 0] / Xg[..., 2] + seq.K[0, 2]).astype(int)
vg = np.round(seq.K[1, 1] * Xg[..., 1] / Xg[..., 2] + seq.K[1, 2]).astype(int)
inner = cov & (ug >= 4) & (ug < 156) & (vg >= 4) & (vg < 116)
true_sim = (pred.D_ji[inner] * pred.D_ii[vg[inner], ug[inner]]).sum(-1)
off_sim = (pred.D_ji[inner] * pred.D_ii[vg[inner], ug[inner] + 4]).sum(-1)
print(f"descriptor similarity: true {np.median(true_sim):.3f}, 4 px off {np.median(off_sim):.3f}")
assert np.median(true_sim) > np.median(off_sim)

# %% [markdown]
# ## 4. A real pair: the RGB-D prior on 7-Scenes
#
# For real RGB-D sequences, `X_ii` is the back-projected depth (holes filled, `C = 1`) and the
# pose carrying `X_jj` into camera i comes from SIFT matches + depth + PnP/RANSAC — never from
# the ground truth, which we only use here to measure the error.

# %%
# The data folder comes from the environment variable MSLAM_DATA (the tests set it); the
# 7-Scenes clip is its seq/7scenes_redkitchen_f000000-000149.
import os

DATA = os.environ.get("MSLAM_DATA")
SEVEN = Path(DATA or "") / "seq" / "7scenes_redkitchen_f000000-000149"
if DATA and SEVEN.is_dir():
    from mslam.datasets import load_sequence
    from mslam.priors.rgbd import RGBDPrior

    real = load_sequence(SEVEN, size=(160, 120))
    rprior = RGBDPrior(real)
    ri, rj = real[20], real[30]
    rpred = rprior.pair(ri, rj)
    check_prediction(rpred)
    T_est, n_inl = rprior.relative_pose(ri, rj)
    T_gt = sim3.mul(sim3.inv(ri.T_WC), rj.T_WC)
    Err = sim3.mul(sim3.inv(T_gt), T_est)
    rot = np.degrees(np.linalg.norm(so3.log(Err[3:7])))
    trans = 100 * np.linalg.norm(T_est[:3] - T_gt[:3])
    print(f"7-Scenes (20, 30): {n_inl} inliers, rotation error {rot:.2f} deg, "
          f"translation error {trans:.2f} cm")  # fmt: skip
    assert rot < 2.0 and trans < 5.0
    show(
        [ri.rgb, ri.depth, rpred.C_ii, rpred.C_ji, pca_rgb(rpred.D_ii)],
        ["rgb i", "depth i", "C_ii (holes = 1)", "C_ji (consistency)", "D_ii (PCA)"],
        "rgbd_prior",
    )
else:
    print(f"the 7-Scenes clip is not at {SEVEN} (set MSLAM_DATA); skipping the real pair")

# %% [markdown]
# ## 5. Upstream's network resolution
#
# MASt3R runs at long side 512 with both sides multiples of 16 (docs/upstream.md §10.1). Intrinsics follow
# by a plain multiplication and the crop offset (docs/upstream.md §10.2).

# %%
big = np.zeros((480, 640, 3), np.uint8)
img512, tr = resize_img(big, 512)
K640 = np.array([[585.0, 0, 320], [0, 585, 240], [0, 0, 1]])
print("640x480 ->", img512.shape[1::-1], "K =", intrinsics_after_resize(K640, tr).round(2).tolist())
assert img512.shape[:2] == (384, 512)

# %% [markdown]
# ## 6. Reference vs fast: moving a pointmap between cameras
#
# Pointmap matching and fusion start by moving points between cameras with a Sim(3) action.
# `mslam_fast.sim3.act` is the Taichi twin of `mslam_ref.sim3.act`: same signature, same
# numbers (the pointmap module itself has no fast twin; it is not on a hot path). At 19 200
# points the kernel call overhead dominates, so the reference may well be faster here.

# %%
import time

import mslam_fast
import mslam_fast.sim3 as fast_sim3

mslam_fast.init("cpu", "f64")
X_j = backproject(fj.depth, seq.K).reshape(-1, 3)
fast_sim3.act(T_ij, X_j[:2])  # compile
t0 = time.perf_counter()
ref_pts = sim3.act(T_ij, X_j)
t1 = time.perf_counter()
fast_pts = fast_sim3.act(T_ij, X_j)
t2 = time.perf_counter()
print(f"{len(X_j)} points: reference {1e3 * (t1 - t0):.2f} ms, fast {1e3 * (t2 - t1):.2f} ms; "
      f"max difference {np.abs(fast_pts - ref_pts).max():.1e}")  # fmt: skip
assert np.allclose(fast_pts, ref_pts, atol=1e-12)

# %% [markdown]
# ## Exercises
#
# 1. The rays `ψ(X_ii)` of a pointmap *are* its camera. From the ground-truth pointmap `X_i`,
#    compute the angle (degrees) between the rays of the top-left and bottom-right pixels and
#    store it in `ex1`; it must agree with the diagonal field of view that `K` implies.
# 2. A 640x480 image with `fx = 585` is resized to MASt3R's 512x384. What is `fx` at the
#    network resolution? Store it in `ex2`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution
psi = X_i / np.linalg.norm(X_i, axis=-1, keepdims=True)
ex1 = float(np.degrees(np.arccos(np.clip(psi[0, 0] @ psi[-1, -1], -1, 1))))
ex2 = 585.0 * 512 / 640

# %%
# Check
corner = np.linalg.inv(seq.K) @ np.array([[0, 159], [0, 119], [1, 1]])
fov = np.degrees(np.arccos((corner[:, 0] @ corner[:, 1]) / np.prod(np.linalg.norm(corner, axis=0))))
assert abs(ex1 - fov) < 1e-9
assert np.isclose(ex2, intrinsics_after_resize(K640, tr)[0, 0])
print("exercises: all correct")
