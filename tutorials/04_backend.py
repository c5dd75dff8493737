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
# # 04 — The backend: global Gauss–Newton over keyframe poses (paper §3.5)
#
# Every graph edge (i, j) holds dense matches both ways and yields two *directed blocks*.
# Block (i ← j) compares the points of keyframe j, moved into camera i by
# `T_ij = T_WCi^-1 T_WCj`, with the matched points of i (ray + distance error, or pixel +
# log-depth with K). Each block adds a 14x14 Hessian block `[[H_ii, H_ij], [H_ji, H_jj]]`;
# summed over the graph they form a block-sparse system in the 7(K-1) pose unknowns (the
# first keyframe is fixed: the gauge). Ten Gauss–Newton steps with left retraction follow.
#
# **What you will learn**
#
# 1. how the ray error of paper Eq. 9 (here its calibrated form, Eq. 10) becomes one 14×14
#    Hessian block per directed edge — built from scratch and checked against the library;
# 2. what a loop closure looks like in the Hessian (blocks far from the diagonal);
# 3. why the first pose must be fixed: the Hessian has exactly **7** zero eigenvalues, one per
#    degree of freedom of a Sim(3) that moves the whole map (6 for SE(3) with known scale);
# 4. Gauss–Newton on the poses, and the Taichi twin against the reference (result and time).

# %%
import matplotlib.pyplot as plt
import numpy as np

from mslam.datasets.synthetic import make_sequence
from mslam_ref import backend, normal_equations, sim3
from mslam_ref.pointmap import backproject

n, W, H = 10, 64, 48
seq = make_sequence("loop", n_frames=n, width=W, height=H, seed=0)
K, T_true = seq.K, seq.T_WC.copy()
D = np.stack([seq[i].depth for i in range(n)])
X = np.stack([backproject(D[i], K) for i in range(n)])
C = np.ones((n, H, W))

# %% [markdown]
# ## Directed blocks from exact projections
# For each ordered pair we match every pixel of j to the nearest pixel of i by projecting with
# the true poses (depth-consistent, inside the image), and keep pairs that share > 20 %.

# %%
ii, jj, idx, valid = [], [], [], []
for i in range(n):
    for j in range(n):
        if i == j:
            continue
        P = sim3.act(sim3.mul(sim3.inv(T_true[i]), T_true[j]), X[j].reshape(-1, 3))
        z = np.where(P[:, 2] > 1e-6, P[:, 2], 1.0)
        u = np.rint(K[0, 0] * P[:, 0] / z + K[0, 2]).astype(int)
        v = np.rint(K[1, 1] * P[:, 1] / z + K[1, 2]).astype(int)
        ok = (P[:, 2] > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        m = np.where(ok, u + W * v, 0)
        ok &= np.abs(D[i].reshape(-1)[m] - P[:, 2]) < 0.05 * P[:, 2]
        if ok.mean() > 0.2:
            ii.append(i), jj.append(j), idx.append(m), valid.append(ok)
ii, jj, idx, valid = map(np.array, (ii, jj, idx, valid))
Q = np.full(valid.shape, 2.0)
print(f"{len(ii)} directed blocks:", list(zip(ii.tolist(), jj.tolist())))
assert len(ii) >= 2 * n - 2

# %% [markdown]
# ## One 14×14 block from scratch
# For block (i ← j) the library returns per pixel the residual `e`, the pose Jacobians
# `J_i = −J_j` and the square-root weights `w = √q/σ` (paper Eq. 5 read as a variance). With the
# Huber weight `ρ = huber(w e)` per component, the block is
# `Σ_k,c ρ w² [J_i; J_j][J_i; J_j]ᵀ` and the gradient `Σ ρ w² e [J_i; J_j]`.

# %%
from mslam_ref.robust import huber_weight

rng = np.random.default_rng(2)
xi = np.concatenate([rng.normal(0, 0.1, (n, 6)), rng.normal(0, 0.05, (n, 1))], axis=1)
xi[0] = 0.0
T0 = sim3.retract(T_true, xi)
cfg = backend.BackendConfig()
graph = backend.pose_graph(X, C, ii, jj, idx, valid, Q, K)  # the data that stays fixed
Hs, gs, cost = backend.linearize(T0, graph, cfg)

b0 = 1  # the directed block (0 <- 9) closes the loop
e, J_i, J_j, w = backend.block_residual_and_jacobian(
    T0[ii[b0]], T0[jj[b0]], X[ii[b0]], X[jj[b0]], C[ii[b0]], C[jj[b0]],
    idx[b0], valid[b0], Q[b0], cfg, K,
)  # fmt: skip
Wc = huber_weight(w * e) * w**2  # (N, c) IRLS weight per component
Jb = np.concatenate([J_i, J_j], axis=2)  # (N, c, 14)
H_mine = np.einsum("nc,nca,ncb->ab", Wc, Jb, Jb)
g_mine = np.einsum("nc,nc,nca->a", Wc, e, Jb)
H_lib = np.block([[Hs[b0, 0], Hs[b0, 1]], [Hs[b0, 2], Hs[b0, 3]]])  # [H_ii, H_ij, H_ji, H_jj]
g_lib = gs[b0].ravel()  # [g_i, g_j]
print(
    f"block {b0} = ({ii[b0]} <- {jj[b0]}): max |H_mine - H_lib| = {np.abs(H_mine - H_lib).max():.2e}"
)
np.testing.assert_allclose(H_mine, H_lib, rtol=1e-9, atol=1e-9 * np.abs(H_lib).max())
np.testing.assert_allclose(g_mine, g_lib, rtol=1e-9, atol=1e-9 * np.abs(g_lib).max())
# J_i = -J_j, so the four 7x7 sub-blocks are ±H_jj
np.testing.assert_allclose(H_mine[:7, :7], -H_mine[:7, 7:], atol=1e-9 * np.abs(H_mine).max())

# %% [markdown]
# ## The Hessian with its loop blocks, and the gauge
# Summing all blocks into the full 7N×7N matrix (no pose fixed yet) gives a block-tridiagonal
# band — consecutive keyframes — plus the **loop-closure blocks** (0, 9) and (9, 0) in the
# corners. Every residual depends on relative poses only, so a common Sim(3) of all poses
# changes nothing: the full Hessian has **7 zero eigenvalues**. Fixing keyframe 0 (dropping its
# rows and columns) removes them — and also removes the loop block from the solved system,
# since it touches keyframe 0; its information is still there, on the diagonal block of 9.

# %%
H_full, _ = normal_equations.assemble_system(Hs, gs, ii, jj, n)
H_full = H_full.toarray()
A, b = normal_equations.assemble_system(Hs, gs, ii - 1, jj - 1, n - 1)
A = A.toarray()
ev_full = np.linalg.eigvalsh(H_full)
ev_pinned = np.linalg.eigvalsh(A)
n_zero = int(np.sum(ev_full < 1e-10 * ev_full[-1]))
print(f"full H: {H_full.shape}, {n_zero} zero eigenvalues; pinned A: {A.shape}, "
      f"smallest/largest eigenvalue {ev_pinned[0] / ev_pinned[-1]:.1e}")  # fmt: skip

fig, ax = plt.subplots(1, 3, figsize=(12, 3.8))
ax[0].spy(H_full, markersize=1)
for blk in (0, n - 1):
    other = n - 1 - blk
    ax[0].add_patch(
        plt.Rectangle((7 * other - 0.5, 7 * blk - 0.5), 7, 7, fill=False, color="r", lw=2)
    )
ax[0].set_title("full H (7N x 7N): loop blocks in red")
ax[1].spy(A, markersize=1)
ax[1].set_title(f"pinned A: {A.shape[0]}x{A.shape[1]}")
ax[2].semilogy(np.abs(ev_full) / ev_full[-1], "o", ms=3, label="full H")
ax[2].semilogy(np.r_[np.full(7, np.nan), ev_pinned / ev_full[-1]], "x", ms=3, label="pinned")
ax[2].axvline(6.5, color="k", lw=0.5)
ax[2].set_title("eigenvalues / largest (sorted)")
ax[2].legend()
plt.tight_layout()
plt.show()
assert n_zero == 7  # the Sim(3) gauge
assert np.abs(H_full[:7, 7 * (n - 1) :]).max() > 0  # the loop block is there
assert ev_pinned[0] > 1e-8 * ev_pinned[-1]
np.testing.assert_allclose(A, A.T, rtol=1e-9, atol=1e-6)

# %% [markdown]
# ## Gauss–Newton, calibrated
# Ten iterations (it stops earlier only if the step is shorter than 1e-8).

# %%
T1, info = backend.solve(T0, graph, backend.BackendConfig())


def traj_err(T):
    e = sim3.log(sim3.mul(T, sim3.inv(T_true)))
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


print(f"iterations {info.iterations}, cost {info.costs[0]:.3g} -> {info.costs[-1]:.3g}")
print(f"trajectory error {traj_err(T0):.4f} -> {traj_err(T1):.4f}")
fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
ax[0].semilogy(info.costs, "o-")
ax[0].set_xlabel("iteration")
ax[0].set_ylabel("robust cost")
for T, style, label in (
    (T_true, "k-o", "truth"),
    (T0, "r--x", "initial"),
    (T1, "b-.", "optimised"),
):
    loop = np.vstack([T[:, :3], T[:1, :3]])
    ax[1].plot(loop[:, 0], loop[:, 1], style, label=label)
ax[1].set_aspect("equal")
ax[1].legend()
plt.show()
assert traj_err(T1) < traj_err(T0) / 10
np.testing.assert_array_equal(T1[0], T0[0])  # the gauge: keyframe 0 never moves

# %% [markdown]
# ## Reference against fast
# `mslam_fast.backend.solve` has the same signature; its kernel accumulates the local 7×7 block
# per pixel chunk in float64 and applies the chain rule once per block on the host.

# %%
import time

import mslam_fast
from mslam_fast import backend as fast_backend

mslam_fast.init(arch="cpu", default_fp="f64")
fast_backend.solve(T0, graph, backend.BackendConfig())  # compile
t = time.perf_counter()
T1_ref, _ = backend.solve(T0, graph, backend.BackendConfig())
t_ref = time.perf_counter() - t
t = time.perf_counter()
T1_fast, _ = fast_backend.solve(T0, graph, backend.BackendConfig())
t_fast = time.perf_counter() - t
print(f"reference {1e3 * t_ref:.0f} ms, fast {1e3 * t_fast:.0f} ms; "
      f"max |T_ref - T_fast| = {np.abs(T1_ref - T1_fast).max():.1e}")  # fmt: skip
np.testing.assert_allclose(T1_fast, T1_ref, atol=1e-6)

# %% [markdown]
# ## Exercises
#
# 1. Drop the loop-closure blocks (the directed blocks between 0 and 9) and solve again. Does
#    the trajectory error grow or shrink? Store the ratio `err_without / err_with` in `ex1`.
# 2. Use the *uncalibrated* ray + distance error (`K=None`) to build the full Hessian at the
#    true poses. How many zero eigenvalues does it have? Store the count in `ex2`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution 1
keep = ~(((ii == 0) & (jj == n - 1)) | ((ii == n - 1) & (jj == 0)))
no_loop = backend.pose_graph(X, C, ii[keep], jj[keep], idx[keep], valid[keep], Q[keep], K)
T_noloop, _ = backend.solve(T0, no_loop, backend.BackendConfig())
ex1 = traj_err(T_noloop) / traj_err(T1)
print(f"without the loop blocks the error is {ex1:.2f}x the error with them")
fig, ax = plt.subplots(figsize=(5, 4))
for T, style, label in (
    (T_true, "k-o", "truth"),
    (T1, "b-.", "with loop blocks"),
    (T_noloop, "r--x", "without"),
):
    ax.plot(T[:, 0], T[:, 1], style, label=label)
ax.set_aspect("equal", adjustable="datalim")
ax.legend()
ax.set_title("keyframe positions after the backend")
plt.show()
# Solution 2
rays = backend.pose_graph(X, C, ii, jj, idx, valid, Q)  # no K: ray + distance
Hs_ray, gs_ray, _ = backend.linearize(T_true, rays, backend.BackendConfig())
H_ray = normal_equations.assemble_system(Hs_ray, gs_ray, ii, jj, n)[0].toarray()
ev_ray = np.linalg.eigvalsh(H_ray)
ex2 = int(np.sum(ev_ray < 1e-10 * ev_ray[-1]))

# %%
# Check
assert ex1 > 1.0, "the loop closure should reduce the error"
assert ex2 == 7, "rays and distances are unchanged by a common Sim(3): 7 zero eigenvalues"
print("exercises: all correct")
