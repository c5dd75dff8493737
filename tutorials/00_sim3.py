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
# # 00 — Sim(3): the pose group of MASt3R-SLAM
#
# MASt3R-SLAM (Murai et al., CVPR 2025, arXiv:2412.12392, §3.1) represents every camera pose as a
# **similarity transform**: a rotation R, a translation t and a scale s > 0, acting on points as
#
# $$T \cdot X = s R X + t.$$
#
# The scale is there because a two-view network predicts pointmaps only up to scale, so poses
# of different keyframes may disagree in scale as well as in position.
#
# This tutorial walks through `mslam_ref.sim3` (the NumPy reference) and checks each identity
# numerically: elements and their layout, Exp/Log, composition, the action on a point cloud, the
# adjoint, and the left-perturbation Jacobian that every residual in the SLAM system uses.
# Conventions: `docs/conventions.md`.
#
# **What you will learn**
#
# 1. the storage layout `[t, q, s]` of a Sim(3) element and the tangent layout `[τ, φ, σ]`;
# 2. Exp and Log, and where their closed forms need series expansions (a figure of the error);
# 3. why the paper's update `T ← Exp(τ) ∘ T` (Eq. 1, a *left* perturbation) gives the point
#    Jacobian `[I | −[P]× | P]` — derived, then checked by finite differences (a figure);
# 4. the Taichi twin `mslam_fast.sim3` against the reference: same numbers, and the time.

# %%
import matplotlib.pyplot as plt
import numpy as np

from mslam_ref import sim3, so3

np.set_printoptions(precision=4, suppress=True)
rng = np.random.default_rng(0)

# %% [markdown]
# ## 1. Elements and tangent vectors
#
# A group element is stored as 8 numbers `[tx, ty, tz, qx, qy, qz, qw, s]` — the layout of
# lietorch and upstream. A tangent vector (an element of the Lie algebra) has 7 numbers
# `xi = [tau, phi, sigma]`: a translation part, a rotation vector (axis x angle), and the log-scale.

# %%
I = sim3.identity()
print("identity:", I)

xi = np.array([0.5, -0.2, 1.0, 0.0, 0.0, np.pi / 2, np.log(2.0)])  # 90 deg about z, scale 2
T = sim3.exp(xi)
print("T = Exp(xi):", T)
print("matrix:\n", sim3.to_matrix(T))
assert np.isclose(T[7], 2.0)  # s = e^sigma
assert np.isclose(np.linalg.norm(T[3:7]), 1.0)  # unit quaternion

# %% [markdown]
# ## 2. Exp and Log
#
# `exp` is the matrix exponential of the 4x4 matrix `[[phi^ + sigma I, tau], [0, 0]]`; the
# translation is not `tau` itself but `W(phi, sigma) tau`. `log` inverts it for rotation angles
# below pi. Let us check both against SciPy's general matrix exponential.

# %%
from scipy.linalg import expm


def hat4(xi):
    M = np.zeros((4, 4))
    M[:3, :3] = so3.hat(xi[3:6]) + xi[6] * np.eye(3)
    M[:3, 3] = xi[:3]
    return M


print("t = W tau:", T[:3], " vs tau:", xi[:3])
assert np.allclose(sim3.to_matrix(T), expm(hat4(xi)), atol=1e-12)
assert np.allclose(sim3.log(T), xi, atol=1e-12)

# Near the identity the closed forms would divide 0 by 0; series expansions take over. The
# figure sweeps the rotation angle from 1e-9 to just below π: Log(Exp(ξ)) returns ξ to
# round-off everywhere, with no jump where the code switches to the series.
angles = np.r_[np.logspace(-9, 0, 40), np.linspace(1.0, np.pi - 1e-6, 40)]
axis = np.array([0.48, -0.6, 0.64])
round_trip = [
    np.abs(sim3.log(sim3.exp(np.r_[0.3, -0.1, 0.2, th * axis, 0.2])) - np.r_[0.3, -0.1, 0.2, th * axis, 0.2]).max()
    for th in angles
]  # fmt: skip
fig, ax = plt.subplots(figsize=(5, 3))
ax.loglog(angles, np.maximum(round_trip, 1e-18), ".-")
ax.set_xlabel("rotation angle θ (rad)")
ax.set_ylabel("max |Log(Exp(ξ)) − ξ|")
ax.set_title("Exp/Log round trip")
plt.show()
assert max(round_trip) < 1e-9

tiny = np.full(7, 1e-9)
assert np.allclose(sim3.log(sim3.exp(tiny)), tiny, rtol=1e-6, atol=1e-15)
# And near a half turn (theta -> pi) Log still recovers the angle.
near_pi = np.array([0.1, 0.2, 0.3, np.pi - 1e-9, 0.0, 0.0, 0.1])
assert np.allclose(sim3.log(sim3.exp(near_pi)), near_pi, atol=1e-9)

# %% [markdown]
# ## 3. Composition and inverse
#
# `mul(A, B)` is `A ∘ B`: apply B first, then A — it equals the product of the 4x4 matrices.
# Names follow the frame convention `T_AB` (maps B-points into A), so `T_AC = T_AB ∘ T_BC`.

# %%
T_AB = sim3.exp(rng.normal(size=7) * 0.5)
T_BC = sim3.exp(rng.normal(size=7) * 0.5)
T_AC = sim3.mul(T_AB, T_BC)
assert np.allclose(sim3.to_matrix(T_AC), sim3.to_matrix(T_AB) @ sim3.to_matrix(T_BC))
assert np.allclose(sim3.mul(T_AB, sim3.inv(T_AB)), sim3.identity(), atol=1e-12)
print("T_AC:", T_AC)

# %% [markdown]
# ## 4. Acting on a point cloud
#
# Every function broadcasts over leading batch axes: one element acts on N points at once.
# Below, a unit cube of points (blue) is mapped by T (orange): rotated 90° about z, doubled
# in size, and moved by t.

# %%
g = np.linspace(0.0, 1.0, 6)
cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)  # (N, 3)
moved = sim3.act(T, cube)  # (N, 3)
assert moved.shape == cube.shape
# Distances scale by s: the action is a similarity.
d0 = np.linalg.norm(cube[1] - cube[0])
d1 = np.linalg.norm(moved[1] - moved[0])
assert np.isclose(d1, 2.0 * d0)

fig = plt.figure(figsize=(5, 5))
ax = fig.add_subplot(projection="3d")
ax.scatter(*cube.T, s=4, label="X")
ax.scatter(*moved.T, s=4, label="T · X")
ax.set_xlabel("x")
ax.set_ylabel("y")
ax.set_zlabel("z")
ax.legend()
plt.show()

# %% [markdown]
# ## 5. The adjoint
#
# Moving a perturbation from one side of T to the other uses the 7x7 adjoint matrix:
#
# $$T \,\mathrm{Exp}(a)\, T^{-1} = \mathrm{Exp}(\mathrm{Ad}(T)\, a).$$
#
# The backend needs the row form `J Ad(T)^-1` (`adjoint_inv_apply`) to carry a Jacobian taken
# in a relative frame back to a world-frame perturbation of a keyframe pose.

# %%
a = rng.normal(size=7) * 0.3
lhs = sim3.to_matrix(T) @ sim3.to_matrix(sim3.exp(a)) @ np.linalg.inv(sim3.to_matrix(T))
rhs = sim3.to_matrix(sim3.exp(sim3.adjoint(T) @ a))
print("max |lhs - rhs| =", np.abs(lhs - rhs).max())
assert np.allclose(lhs, rhs, atol=1e-12)

J = rng.normal(size=7)
assert np.allclose(sim3.adjoint_inv_apply(T, J), J @ np.linalg.inv(sim3.adjoint(T)))

# %% [markdown]
# ## 6. Left perturbations and the point Jacobian
#
# MASt3R-SLAM updates poses on the **left** (paper Eq. 1): `T <- Exp(xi) · T` (`retract`). For a
# transformed point `P = T · X`, a small left perturbation moves it to
# `P + tau + phi x P + sigma P`, so
#
# $$\frac{\partial P}{\partial \xi} = [\, I \mid -[P]_\times \mid P \,] \in \mathbb{R}^{3 \times 7}.$$
#
# We compare this with central finite differences taken *on the manifold*.

# %%
X = np.array([0.3, -1.0, 2.0])
P, J_analytic = sim3.act_and_jacobian(T, X)
eps = 1e-6
J_fd = np.stack(
    [
        (sim3.act(sim3.retract(T, eps * e), X) - sim3.act(sim3.retract(T, -eps * e), X)) / (2 * eps)
        for e in np.eye(7)
    ],
    axis=1,
)
print("analytic:\n", J_analytic)
print("max |analytic - finite differences| =", np.abs(J_analytic - J_fd).max())
assert np.allclose(J_analytic, J_fd, atol=1e-7)

# From scratch: the same Jacobian from P alone, as derived above.
J_mine = np.concatenate([np.eye(3), -so3.hat(P), P[:, None]], axis=1)
assert np.allclose(J_mine, J_analytic, atol=1e-12)

# The finite-difference error against the step: truncation error ~ eps² on the right,
# round-off ~ 1e-16/eps on the left — the classic V that tells a correct Jacobian.
steps = np.logspace(-10, -1, 19)
fd_err = []
for h in steps:
    J_h = np.stack(
        [(sim3.act(sim3.retract(T, h * e), X) - sim3.act(sim3.retract(T, -h * e), X)) / (2 * h) for e in np.eye(7)],
        axis=1,
    )  # fmt: skip
    fd_err.append(np.abs(J_h - J_analytic).max())
fig, ax = plt.subplots(figsize=(5, 3))
ax.loglog(steps, fd_err, "o-")
ax.set_xlabel("finite-difference step")
ax.set_ylabel("max |J_fd − J|")
ax.set_title("left-perturbation Jacobian vs finite differences")
plt.show()
assert min(fd_err) < 1e-8

# %% [markdown]
# ## 7. Reference vs fast
#
# `mslam_fast.sim3` has the same functions with the same signatures, written as Taichi kernels
# (one parallel loop over the batch). Precision and backend are chosen once with
# `mslam_fast.init(arch, default_fp)`; the first call compiles the kernel (about a second).

# %%
import time

import mslam_fast
import mslam_fast.sim3 as fast_sim3

mslam_fast.init("cpu", "f64")
Ts = sim3.exp(rng.normal(size=(200_000, 7)) * 0.5)
Xs = rng.normal(size=(200_000, 3))
fast_sim3.act(Ts[:2], Xs[:2])  # compile once

t0 = time.perf_counter()
ref = sim3.act(Ts, Xs)
t1 = time.perf_counter()
out = fast_sim3.act(Ts, Xs)
t2 = time.perf_counter()
print(
    f"reference {1e3 * (t1 - t0):.1f} ms, fast {1e3 * (t2 - t1):.1f} ms (one run, not a benchmark)"
)
print("max |fast - reference| =", np.abs(out - ref).max())
assert np.allclose(out, ref, rtol=1e-12, atol=1e-12)

fig, ax = plt.subplots(figsize=(4, 2.5))
ax.barh(["reference (NumPy)", "fast (Taichi)"], [1e3 * (t1 - t0), 1e3 * (t2 - t1)])
ax.set_xlabel("ms for 200 000 point actions")
plt.show()

# %% [markdown]
# ## Exercises
#
# 1. Write the action `T · X = s R X + t` yourself from the 8 stored numbers (use
#    `so3.to_matrix` for R) and apply it to `cube`; store the result in `ex1`.
# 2. Compose two elements in both orders. Sim(3) is not commutative: store
#    `‖Log(A∘B) − Log(B∘A)‖` for `A = T_AB`, `B = T_BC` in `ex2`.
# 3. How many numbers store an element, and how many degrees of freedom does it have?
#    Store the pair in `ex3`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution
ex1 = T[7] * cube @ so3.to_matrix(T[3:7]).T + T[:3]
ex2 = float(np.linalg.norm(sim3.log(sim3.mul(T_AB, T_BC)) - sim3.log(sim3.mul(T_BC, T_AB))))
ex3 = (8, 7)

# %%
# Check
assert np.allclose(ex1, sim3.act(T, cube), atol=1e-12)
assert ex2 > 1e-3
assert ex3 == (len(sim3.identity()), 7)
print("exercises: all correct")
