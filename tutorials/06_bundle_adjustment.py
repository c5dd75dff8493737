# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 06 — Bundle adjustment: Levenberg–Marquardt with a Schur complement
#
# A bundle adjuster refines camera poses and 3-D points together so that the points project
# onto their observed pixels. This tutorial builds a small synthetic problem, looks at the
# *arrow-shaped* normal equations, eliminates the points with a Schur complement, runs g2o's
# Levenberg–Marquardt schedule, and compares the NumPy reference with the Taichi kernels.
# It runs as a plain script (`MPLBACKEND=Agg python tutorials/06_bundle_adjustment.py`) and
# writes no files.

# %%
import itertools
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")

import matplotlib.pyplot as plt
import numpy as np

import mslam_ref.ba as ref_ba
from mslam_ref.ba import lm, schur, synthetic
from mslam_ref.ba.robust import RobustKernel

# %% [markdown]
# ## 1. A small problem
# Six SE(3) cameras (g2o `VertexSE3Expmap`, world to camera) on an arc look at 40 points; each
# point is seen by 3 cameras, 30% of the edges are stereo `(u, v, ur)`, the pixels carry
# 0.5 px noise and the initial estimate is the truth perturbed by ~2 cm / 0.02 rad.

# %%
problem, truth = synthetic.make_pinhole_problem(
    n_cams=6,
    n_points=40,
    views=3,
    stereo_fraction=0.3,
    seed=0,
    kernel=RobustKernel("huber", np.sqrt(5.991)),
)
M, P, O = len(problem.poses), len(problem.points), len(problem.obs_cam)
print(f"M={M} cameras, P={P} points, O={O} observations ({problem.is_stereo.sum()} stereo)")

# %% [markdown]
# ## 2. The normal equations are arrow-shaped
# With $J = [J_c, J_p]$ and weights $w$, $H = J^\top W J$ has a block-diagonal camera part
# $U$ (6x6 blocks), a block-diagonal point part $V$ (3x3 blocks) and the couplings $W$ (one 6x3
# block per observation):
#
# $$\begin{bmatrix} U & W \\ W^\top & V \end{bmatrix}
#   \begin{bmatrix} \Delta c \\ \Delta l \end{bmatrix} =
#   \begin{bmatrix} b_c \\ b_l \end{bmatrix}$$

# %%
cams, pts = problem.params()
st = schur.build_structure(problem.obs_cam, problem.obs_pt, M, P, problem.cam_dof)
r, Jc, Jp = problem.linearize(ref_ba, cams, pts)
U, V, W, bc, bl = schur.normal_blocks(r, Jc, Jp, problem.information, st)

d = problem.cam_dof
H = np.zeros((M * d + 3 * P,) * 2)
for i in range(M):
    H[i * d : (i + 1) * d, i * d : (i + 1) * d] = U[i]
for j in range(P):
    H[M * d + 3 * j : M * d + 3 * j + 3, M * d + 3 * j : M * d + 3 * j + 3] = V[j]
for e, (i, j) in enumerate(zip(st.obs_cam, st.obs_pt)):
    H[i * d : (i + 1) * d, M * d + 3 * j : M * d + 3 * j + 3] += W[e]
    H[M * d + 3 * j : M * d + 3 * j + 3, i * d : (i + 1) * d] += W[e].T

fig, ax = plt.subplots(1, 2, figsize=(9, 4.3))
ax[0].spy(np.abs(H) > 0, markersize=0.6)
ax[0].set_title("H: the arrow (cameras first, then points)")
S_dense = schur.dense_reduced(schur.schur_complement(U, V, W, bc, bl, 0.0, st)[0], st)
ax[1].spy(np.abs(S_dense) > 0, markersize=2)
ax[1].set_title("reduced camera system S")
plt.tight_layout()

assert np.allclose(H, H.T)
assert np.count_nonzero(H[M * d :, M * d :]) <= 9 * P  # V is block-diagonal

# %% [markdown]
# ## 3. Eliminating the points (Schur complement)
# $V$ inverts block by block, so
# $S = U - W V^{-1} W^\top$, $\;S\,\Delta c = b_c - W V^{-1} b_l$, and then
# $\Delta l = V^{-1}(b_l - W^\top \Delta c)$. The reduced system has only $6M$ unknowns.
# We check it against the dense solve of the full damped system.

# %%
lam = 1e-3 * np.abs(np.diag(H)).max()
dc, dl = lm.solve_damped((U, V, W, bc, bl), lam, st)
x = np.linalg.solve(H + lam * np.eye(len(H)), np.r_[bc.ravel(), bl.ravel()])
print("max |Schur step - dense step| =", np.abs(np.r_[dc.ravel(), dl.ravel()] - x).max())
assert np.allclose(np.r_[dc.ravel(), dl.ravel()], x, atol=1e-9 * np.abs(x).max())

# %% [markdown]
# ## 4. Levenberg–Marquardt (g2o's schedule)
# $\lambda_0 = 10^{-5}\max\operatorname{diag}H$; a trial is accepted when the gain ratio
# $\rho = (F - F_{new}) / (\Delta x^\top(\lambda \Delta x + b))$ is positive, and then
# $\lambda \leftarrow \lambda\,\mathrm{clamp}(1 - (2\rho - 1)^3, 1/3, 2/3)$; otherwise
# $\lambda \leftarrow \nu\lambda$, $\nu \leftarrow 2\nu$.

# %%
res = lm.optimize(problem, lm.LMConfig(iterations=20))
costs = [res.initial_cost] + [h["cost"] for h in res.history]
truth_cost = lm.optimize(truth, lm.LMConfig(iterations=0)).initial_cost
print(
    f"cost {res.initial_cost:.1f} -> {res.final_cost:.3f} in {res.iterations} iterations "
    f"({res.stop_reason}); cost at the ground truth {truth_cost:.3f}"
)
plt.figure(figsize=(5, 3.3))
plt.semilogy(costs, "o-")
plt.axhline(truth_cost, color="gray", ls="--", label="ground truth")
plt.xlabel("iteration")
plt.ylabel("cost 0.5 sum rho")
plt.legend()
plt.title("LM convergence")
assert all(b <= a for a, b in itertools.pairwise(costs))
assert res.final_cost <= truth_cost

# %% [markdown]
# ## 5. Reference vs fast kernels
# The driver is the same; only the kernel set changes (`mslam_fast.ba`: Taichi kernels for
# the residuals/Jacobians, the block assembly, the Schur products and the back-substitution).

# %%
import mslam_fast.ba as fast_ba

res_fast = lm.optimize(problem, lm.LMConfig(iterations=20), fast_ba)
print(f"reference {res.final_cost:.9f}  fast {res_fast.final_cost:.9f}")
assert abs(res_fast.final_cost - res.final_cost) <= 1e-6 * res.final_cost
assert np.allclose(res_fast.problem.points, res.problem.points, atol=1e-6)
print(
    "profile (fast, s; the first call includes the Taichi compilation):",
    {k: round(v, 4) for k, v in res_fast.profile.items()},
)
