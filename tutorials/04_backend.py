# %% [markdown]
# # 04 — The backend: global Gauss–Newton over keyframe poses (paper §3.5)
#
# Every graph edge (i, j) holds dense matches both ways and yields two *directed blocks*.
# Block (i ← j) compares the points of keyframe j, moved into camera i by
# `T_ij = T_WCi^-1 T_WCj`, with the matched points of i (ray + distance error, or pixel +
# log-depth with K). Each block adds a 14x14 Hessian block `[[H_ii, H_ij], [H_ji, H_jj]]`;
# summed over the graph they form a block-sparse system in the 7(K-1) pose unknowns (the
# first keyframe is fixed: the gauge). Ten Gauss–Newton steps with left retraction follow.

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
# ## The block-sparse Hessian
# The loop closes: block (0, 9) links the last keyframe to the first. Keyframe 0 is fixed, so
# its rows and columns are dropped.

# %%
rng = np.random.default_rng(2)
xi = np.concatenate([rng.normal(0, 0.1, (n, 6)), rng.normal(0, 0.05, (n, 1))], axis=1)
xi[0] = 0.0
T0 = sim3.retract(T_true, xi)
graph = backend.pose_graph(X, C, ii, jj, idx, valid, Q, K)
Hs, gs, cost = backend.linearize(T0, graph)
A, b = normal_equations.assemble_system(Hs, gs, ii - 1, jj - 1, n - 1)
fig, ax = plt.subplots(figsize=(4, 4))
ax.spy(A.toarray(), markersize=1)
ax.set_title(f"A: {A.shape[0]}x{A.shape[1]}, {A.nnz} non-zeros")
plt.close(fig)
assert A.shape == (7 * (n - 1), 7 * (n - 1))
np.testing.assert_allclose(A.toarray(), A.toarray().T, rtol=1e-9, atol=1e-6)

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
plt.close(fig)
assert traj_err(T1) < traj_err(T0) / 10
np.testing.assert_array_equal(T1[0], T0[0])  # the gauge: keyframe 0 never moves
