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
# # 05 — The full system: tracking, keyframes, the graph, loop closure, the backend
#
# MASt3R-SLAM (Murai et al., CVPR 2025, arXiv:2412.12392, §3) runs a *frontend* that tracks
# every frame against the last keyframe and a *backend* that keeps a graph of keyframes and
# optimises all their poses. Upstream runs them in separate processes; here (as upstream's
# `single_thread` evaluation mode) the backend runs synchronously after every new keyframe:
#
# 1. **INIT**: the first frame's mono pointmap becomes keyframe 0 (pose = identity).
# 2. **TRACKING**: `prior.pair(frame, keyframe)` → matching → IRLS Gauss–Newton on the Sim(3)
#    `T_CkCf` → fusion of the keyframe pointmap → new keyframe when too few good matches remain.
# 3. **Graph + backend** for each new keyframe `k`: an edge to `k-1` (always accepted) and to the
#    retrieval candidates (accepted when enough pixels match: the loop closures); then the global
#    Gauss–Newton over all keyframe poses (keyframe 0 fixed).
# 4. **RELOC** when tracking fails (see `synthetic:jump`).
#
# This tutorial runs the system on a short synthetic loop and draws the keyframe graph, the
# loop-closure edge and the trajectory before and after the backend.
#
# **What you will learn**
#
# 1. how the pieces of tutorials 02–04 and 07 fit into one loop (paper Fig. 3, §3.3–3.6);
# 2. what the backend (§3.5) corrects: keyframe poses from tracking alone against the poses
#    after the global solves;
# 3. drift with and without loop closure (§3.4; the paper's Table 7 ablation, in miniature);
# 4. that the `ref` and `fast` kernel sets give the same trajectory, and how long each takes.

# %%
import time

import matplotlib.pyplot as plt
import numpy as np

from mslam import evaluate
from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam_ref import sim3

# %% [markdown]
# ## Run
#
# `synthetic:loop:24:64x48` is 24 frames at 64×48 pixels of the `loop` path: an ellipse around a
# procedural room whose last frames revisit the first. The *synthetic prior* turns the rendered
# depth into MASt3R-like pointmaps with noise (per-pair scale and Sim(3) errors, smooth depth
# noise, outliers), so the system has real errors to correct. The kernel set `fast` uses the
# Taichi kernels (the reference `ref` gives the same answer, only slower).

# %%
cfg = load_config()  # the packaged base.yaml: upstream's keys and defaults
source = open_source("synthetic:loop:24:64x48", cfg)
kernels = load_kernels("fast")
system, meta = run_slam(source, cfg, kernels)
seq = source.sequence
print(f"{meta['seconds']:.1f} s, {len(system.keyframes)} keyframes, {len(system.graph)} edges")
for e in system.graph.edges:
    print(f"  edge ({e.i:2d}, {e.j:2d})  {e.kind:11s}  match fraction {e.match_frac:.2f}")

# %%
assert system.stats.lost_frames == 0
assert len(system.keyframes) >= 4
loops = [e for e in system.graph.edges if e.kind == "retrieval"]
assert loops, "expected at least one loop-closure edge"
K = len(system.keyframes)
closing = max(loops, key=lambda e: e.j - e.i)
assert closing.i <= 2 and closing.j >= K - 3, "the longest retrieval edge closes the loop"

# %% [markdown]
# ## Before and after the backend
#
# Every keyframe remembers the pose it was created with (`T_WC_init`: tracking alone, chained
# from keyframe to keyframe) and has its final pose after all backend solves (`T_WC`). Tracking
# drifts a little with every keyframe; the loop-closure edge ties the end back to the start and
# the global solve spreads the correction along the loop. Both are compared with ground truth
# after a Sim(3) alignment (the pointmaps are only defined up to scale).

# %%
kf_ts = np.array([kf.frame.timestamp for kf in system.keyframes])
before = np.stack([kf.T_WC_init for kf in system.keyframes])
after = system.keyframes.poses()
ate_before = evaluate.ate(kf_ts, before, seq.timestamps, seq.T_WC)
ate_after = evaluate.ate(kf_ts, after, seq.timestamps, seq.T_WC)
print(
    f"keyframe ATE before the backend {ate_before.rmse * 100:.2f} cm, after {ate_after.rmse * 100:.2f} cm"
)
assert ate_after.rmse < ate_before.rmse

# %%
gt = seq.T_WC[:, :3]
fig, axes = plt.subplots(1, 2, figsize=(11, 5))
ax = axes[0]
ax.plot(gt[:, 0], gt[:, 1], "-", color="0.6", lw=3, label="ground truth")
ax.plot(*ate_before.aligned_positions[:, :2].T, "o--", color="C1", ms=4, label="before backend")
ax.plot(*ate_after.aligned_positions[:, :2].T, "o-", color="C0", ms=4, label="after backend")
ax.set_title("keyframe trajectory (top view, Sim(3)-aligned)")
ax.set_aspect("equal", adjustable="datalim")
ax.legend(fontsize=8)

ax = axes[1]
P = ate_after.aligned_positions
for e in system.graph.edges:
    style = {"consecutive": ("0.6", 1.0), "retrieval": ("C3", 2.0), "reloc": ("C2", 2.0)}[e.kind]
    ax.plot(*P[[e.i, e.j], :2].T, "-", color=style[0], lw=style[1])
ax.plot(*P[:, :2].T, "o", color="C0", ms=5)
for k, p in enumerate(P):
    ax.annotate(str(k), p[:2], fontsize=7, xytext=(3, 3), textcoords="offset points")
ax.plot([], [], "-", color="0.6", label="consecutive edge")
ax.plot([], [], "-", color="C3", lw=2, label="loop-closure edge")
ax.set_title("keyframe graph")
ax.set_aspect("equal", adjustable="datalim")
ax.legend(fontsize=8)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## Every frame, not only keyframes
#
# The frontend stores each frame's pose relative to its keyframe (`T_CkCf`), so the per-frame
# trajectory written to `trajectory.txt` is composed with the *final* keyframe poses and benefits
# from the backend too (upstream writes keyframes only).

# %%
idx, ts, T = system.frame_poses()
res = evaluate.ate(ts, T, seq.timestamps, seq.T_WC)
path = float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum())
print(
    f"all {len(idx)} frames: ATE {res.rmse * 100:.2f} cm = {100 * res.rmse / path:.2f}% of the {path:.2f} m path"
)
assert len(idx) == len(seq)
assert res.rmse < 0.03 * path
# the relative pose of a tracked frame, composed with its keyframe, gives its world pose
p = next(p for p in system.poses if p.status == "tracked")
T_W = sim3.mul(system.keyframes[p.kf].T_WC, p.T_CkCf)
assert np.allclose(T_W, T[list(idx).index(p.index)])

# %% [markdown]
# ## Drift with and without loop closure
#
# The same run with retrieval switched off (a score threshold no candidate reaches): only
# consecutive edges, so nothing ties the end of the loop to its start. The per-keyframe error
# after alignment grows along the loop; with the loop-closure edge it stays flat.

# %%
cfg_nolc = load_config(overrides=["retrieval.min_thresh=1e9"])
system_nolc, _ = run_slam(open_source("synthetic:loop:24:64x48", cfg_nolc), cfg_nolc, kernels)
assert not [e for e in system_nolc.graph.edges if e.kind == "retrieval"]
kf_ts_nolc = np.array([kf.frame.timestamp for kf in system_nolc.keyframes])
ate_nolc = evaluate.ate(kf_ts_nolc, system_nolc.keyframes.poses(), seq.timestamps, seq.T_WC)
print(
    f"keyframe ATE without loop closure {100 * ate_nolc.rmse:.2f} cm, with {100 * ate_after.rmse:.2f} cm"
)
fig, ax = plt.subplots(figsize=(6, 3))
ax.plot(100 * ate_nolc.errors, "o--", color="C1", label="without loop closure")
ax.plot(100 * ate_after.errors, "o-", color="C0", label="with loop closure")
ax.set_xlabel("keyframe")
ax.set_ylabel("position error (cm)")
ax.legend()
plt.show()
assert ate_after.rmse < ate_nolc.rmse

# %% [markdown]
# ## The `ref` and `fast` kernel sets
#
# The whole loop with the NumPy reference kernels and with the Taichi kernels, on a tiny
# sequence (the reference is slow: about 8x slower at 128x96, see the README). Same keyframes,
# same poses to round-off.

# %%
runs = {}
for name in ("ref", "fast"):
    t0 = time.perf_counter()
    sys_k, _ = run_slam(open_source("synthetic:loop:6:32x24", cfg), cfg, load_kernels(name))
    runs[name] = (sys_k.keyframes.poses(), time.perf_counter() - t0)
print(f"ref {runs['ref'][1]:.2f} s, fast {runs['fast'][1]:.2f} s; "
      f"max pose difference {np.abs(runs['ref'][0] - runs['fast'][0]).max():.1e}")  # fmt: skip
fig, ax = plt.subplots(figsize=(4, 2.2))
ax.barh(["ref", "fast"], [runs["ref"][1], runs["fast"][1]])
ax.set_xlabel("seconds (6 frames, 32x24)")
plt.show()
assert runs["ref"][0].shape == runs["fast"][0].shape
np.testing.assert_allclose(runs["ref"][0], runs["fast"][0], atol=1e-6)

# %% [markdown]
# ## Looking inside a run: a Rerun recording
#
# A run can be watched frame by frame. `run_slam(..., observer=tap)` calls the tap after every
# frame; the `SystemTap` turns what changed (the frame's pose and status, new or refined keyframe
# pointmaps, keyframe poses moved by the backend, graph edges, relocalisations) into calls of a
# narrow observer interface, here a `RerunRecorder` that writes a `.rrd` file for the Rerun
# viewer (`rerun run.rrd`; `mslam run ... --rerun OUT/run.rrd` does the same from the command
# line, docs/outputs.md). No display is needed to record.
#
# The recording keeps each frame's pose *as it was known at that frame*; the trajectory file
# has the final poses, after every backend solve. Reading the recording back shows the
# difference: the backend's corrections, frame by frame.

# %%
import tempfile
from pathlib import Path

from rerun.chunk import RrdReader

from mslam.export import SystemTap
from mslam.export.rerun_log import RerunRecorder

rrd = Path(tempfile.mkdtemp()) / "run.rrd"
recorder = RerunRecorder(rrd)
tap = SystemTap(recorder)
src12 = open_source("synthetic:loop:12:64x48", cfg)
system12, _ = run_slam(src12, cfg, kernels, observer=tap)
tap.finish(system12)  # pointmaps refined since they were last sent
recorder.close()

entities: dict[str, list] = {}
for chunk in RrdReader(str(rrd)).store().stream():
    entities.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
print(f"{rrd.stat().st_size / 1e6:.1f} MB; entities:")
print("  " + ", ".join(sorted(e for e in entities if not e.startswith("/__"))))


def rows(entity: str, column: str) -> list:
    return [
        v
        for b in entities[entity]
        if column in b.schema.names
        for v in b.column(column).to_pylist()
    ]


frames_rec = np.array(rows("/world/camera", "frame"))
P_rec = np.array(rows("/world/camera", "Transform3D:translation")).reshape(-1, 3)
idx12, _, T12 = system12.frame_poses()
P_final = T12[np.searchsorted(idx12, frames_rec), :3]
fig, ax = plt.subplots(figsize=(6, 3))
ax.plot(frames_rec, 100 * np.linalg.norm(P_rec - P_final, axis=1), "o-")
ax.set_xlabel("frame")
ax.set_ylabel("pose at the time - final pose (cm)")
ax.set_title("what the backend changed after each frame was tracked")
plt.show()

# %%
assert sorted(rows("/status", "frame")) == list(range(12))
assert len(P_rec) == len(idx12)  # one pose per posed frame
assert np.allclose(P_rec[0], 0.0)  # frame 0 is keyframe 0, the world origin
assert all(f"/world/keyframes/{k}/points" in entities for k in range(len(system12.keyframes)))

# %% [markdown]
# ## Exercises
#
# 1. Which fraction of the 24 frames became keyframes? Store it in `ex1`.
# 2. The trajectory file holds *every* frame: compose the world pose of the last tracked frame
#    from its keyframe's final pose and its stored `T_CkCf`, and store it in `ex2`.
#
# The solutions follow; try first, then run the check cell.

# %%
# Solution
ex1 = len(system.keyframes) / len(seq)
last = [p for p in system.poses if p.status == "tracked"][-1]
ex2 = sim3.mul(system.keyframes[last.kf].T_WC, last.T_CkCf)

# %%
# Check
assert np.isclose(ex1, len(system.keyframes) / 24)
assert np.allclose(ex2, T[list(idx).index(last.index)], atol=1e-12)
print("exercises: all correct")

# %% [markdown]
# From the command line the same run is `mslam run synthetic:loop:24:64x48 --out DIR`, which
# also writes the point cloud, `summary.json` and a trajectory plot (see `docs/system.md`).
