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
# writes no files. (Bundle adjustment is not part of the MASt3R-SLAM paper; the design is in
# `docs/ba.md`, whose symbols this chapter uses: $U, V$ diagonal blocks, $E$ the camera–point
# coupling, $g$ the right-hand side.)
#
# **What you will learn**
#
# 1. why the normal equations of bundle adjustment are arrow-shaped;
# 2. the Schur complement, written from scratch — undamped ($\lambda = 0$, the exact elimination)
#    and damped (what LM factors) — checked against the library and against a dense solve;
# 3. the gauge: the undamped system has **6** zero eigenvalues here (an SE(3) moving the whole
#    scene; the stereo edges fix the scale — a monocular problem has 7), which damping lifts;
# 4. g2o's LM schedule: $\lambda$ and the gain ratio $\varrho$ per iteration, and the residuals
#    before and after;
# 5. the Taichi kernels against the NumPy reference.

# %%
import itertools
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

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
# With $J = [J_c, J_p]$ and per-edge weights $w_e$, $H = J^\top \mathrm{diag}(w) J$ has a
# block-diagonal camera part $U$ (6x6 blocks), a block-diagonal point part $V$ (3x3 blocks) and
# the couplings $E$ (one 6x3 block per observation; the library calls the array `W`):
#
# $$\begin{bmatrix} U & E \\ E^\top & V \end{bmatrix}
#   \begin{bmatrix} \Delta c \\ \Delta l \end{bmatrix} =
#   \begin{bmatrix} g_c \\ g_l \end{bmatrix}$$
#
# The right panel is the *undamped* reduced camera matrix $S(0) = U - E V^{-1} E^\top$.

# %%
cams, pts = problem.params()
st = schur.build_structure(problem.obs_cam, problem.obs_pt, M, P, problem.cam_dof)
r, Jc, Jp = problem.linearize(ref_ba, cams, pts)  # -> ref_ba.cameras.pinhole_linearize (masked)
r_cam, Jc_cam, Jp_cam = ref_ba.cameras.pinhole_linearize(
    cams, problem.intrinsics, pts, problem.obs_cam, problem.obs_pt, problem.meas,
    problem.is_stereo.astype(float),
)  # fmt: skip
assert np.allclose(r_cam, r)  # residual = projection - measurement, (O, 3) with stereo u_r
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
ax[1].set_title("undamped reduced camera matrix S(0)")
plt.tight_layout()

assert np.allclose(H, H.T)
assert np.count_nonzero(H[M * d :, M * d :]) <= 9 * P  # V is block-diagonal

# %% [markdown]
# ## 3. Eliminating the points (Schur complement)
# $V$ inverts block by block. LM adds $\lambda I$ to $H$, so the system it solves is the
# **damped** one:
# $S(\lambda) = (U + \lambda I) - E (V + \lambda I)^{-1} E^\top$,
# $\;S(\lambda)\,\Delta c = g_c - E (V + \lambda I)^{-1} g_l$, and then
# $\Delta l = (V + \lambda I)^{-1}(g_l - E^\top \Delta c)$. The reduced system has only $6M$
# unknowns. $S(0)$, drawn above, is the exact elimination of the undamped $H$.
#
# From scratch first: both complements from the dense $H$, against the library.

# %%
lam = 1e-3 * np.abs(np.diag(H)).max()
Hcc, Hcp, Hpp = H[: M * d, : M * d], H[: M * d, M * d :], H[M * d :, M * d :]
for lam_k in (0.0, lam):
    S_mine = Hcc + lam_k * np.eye(M * d) - Hcp @ np.linalg.solve(Hpp + lam_k * np.eye(3 * P), Hcp.T)
    S_lib = schur.dense_reduced(schur.schur_complement(U, V, W, bc, bl, lam_k, st)[0], st)
    print(f"lambda = {lam_k:.3g}: max |S_mine - S_lib| = {np.abs(S_mine - S_lib).max():.1e}")
    assert np.allclose(S_mine, S_lib, atol=1e-9 * np.abs(S_lib).max())

# The gauge: S(0) inherits H's null space. Six zero eigenvalues (a rigid motion of everything;
# the stereo edges fix the scale), lifted by the damping.
ev0 = np.linalg.eigvalsh(S_dense)
ev_lam = np.linalg.eigvalsh(S_mine)
n_zero = int(np.sum(ev0 < 1e-10 * ev0[-1]))
print(f"S(0): {n_zero} zero eigenvalues; S(lambda): smallest {ev_lam[0]:.3g}")
assert n_zero == 6 and ev_lam[0] > 0.5 * lam

# The damped step through the Schur complement equals the dense damped solve.

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
fig, ax = plt.subplots(1, 3, figsize=(12, 3.3))
ax[0].semilogy(costs, "o-")
ax[0].axhline(truth_cost, color="gray", ls="--", label="ground truth")
ax[0].set_xlabel("iteration")
ax[0].set_ylabel("cost 0.5 sum rho")
ax[0].legend()
ax[0].set_title("LM convergence")
ax[1].semilogy([h["lambda"] for h in res.history], "o-")
ax[1].set_xlabel("iteration")
ax[1].set_title("λ after each iteration")
ax[2].plot([h["gain"] for h in res.history], "o-")
ax[2].axhline(0, color="k", lw=0.5)
ax[2].set_xlabel("iteration")
ax[2].set_title("gain ratio ϱ (accepted if > 0)")
plt.tight_layout()
plt.show()

r_before = problem.residuals(ref_ba, *problem.params())
r_after = res.problem.residuals(ref_ba, *res.problem.params())
fig, ax = plt.subplots(figsize=(5, 3))
bins = np.linspace(0, np.percentile(np.linalg.norm(r_before, axis=-1), 99), 40)
ax.hist(np.linalg.norm(r_before, axis=-1), bins, alpha=0.6, label="before")
ax.hist(np.linalg.norm(r_after, axis=-1), bins, alpha=0.6, label="after")
ax.set_xlabel("|residual| per observation (px)")
ax.legend()
ax.set_title("BA residuals before / after")
plt.show()
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
import time

t0 = time.perf_counter()
lm.optimize(problem, lm.LMConfig(iterations=20))
t_ref = time.perf_counter() - t0
t0 = time.perf_counter()
lm.optimize(problem, lm.LMConfig(iterations=20), fast_ba)  # compiled by now
t_fast = time.perf_counter() - t0
print(f"whole solve: reference {1e3 * t_ref:.0f} ms, fast {1e3 * t_fast:.0f} ms "
      "(a tiny problem: the kernels only pay off at BAL sizes, see benchmarks/RESULTS.md)")  # fmt: skip
print(
    "profile (fast, s; the first call includes the Taichi compilation):",
    {k: round(v, 4) for k, v in res_fast.profile.items()},
)

# %% [markdown]
# ## Exercises
#
# 1. Replay g2o's schedule by hand: from the first iteration's λ and the second iteration's
#    gain ratio (one trial, accepted), what λ does the second iteration end with? Store it in
#    `ex1`.
# 2. Remove the damping: solve the undamped reduced system $S(0)\,\Delta c = \ldots$ with
#    `np.linalg.lstsq` and report the rank of $S(0)$ in `ex2`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution
h0, h1 = res.history[0], res.history[1]
ex1 = h0["lambda"] * min(max(1 - (2 * h1["gain"] - 1) ** 3, 1 / 3), 2 / 3)
ex2 = int(np.linalg.matrix_rank(S_dense, tol=1e-10 * np.abs(S_dense).max()))

# %%
# Check
assert h1["trials"] == 1 and np.isclose(ex1, h1["lambda"], rtol=1e-12)
assert ex2 == M * d - 6
print("exercises: all correct")
