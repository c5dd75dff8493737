# %% [markdown]
# # 07 — RGB only: the two-view prior and why the poses are Sim(3)
#
# MASt3R-SLAM is monocular: its prior turns two images into two pointmaps *up to an unknown
# scale*, so every keyframe's pointmap has its own scale and the poses are Sim(3), not SE(3)
# (paper §3.1). Without the network, `--prior twoview` (`mslam_ref.priors.twoview`,
# docs/priors.md) makes the same kind of output from classical geometry: DIS optical flow, the
# essential matrix and dense triangulation. The translation of an essential matrix has no
# length, so each pair's pointmaps come in their own arbitrary (normalised) scale — exactly the
# situation Sim(3) tracking and the backend exist for.
#
# This tutorial runs the system on the RGB stream of 7-Scenes redkitchen (frames 0–149, every
# second one, depth ignored, uncalibrated; a rendered sequence when the shared data is absent)
# and compares each keyframe's pointmap scale with ground truth, with
# the pose each keyframe was created with (tracking only) and with its final pose (after the
# backend and its loop-closure edges).

# %%
import os
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import matplotlib.pyplot as plt
import numpy as np

from mslam_ref import evaluate
from mslam_ref.config import load_config
from mslam_ref.kernels import load_kernels
from mslam_ref.system import open_source, run_slam

try:
    ROOT = Path(__file__).resolve().parents[1]
except NameError:  # run as a notebook from tutorials/
    ROOT = Path.cwd().parent
DATA = ROOT.parent / "shared/data/seq/7scenes_redkitchen_f000000-000149"
if DATA.is_dir():
    # Every second frame (75 frames): twice the parallax per frame, half the run time.
    source, overrides = str(DATA), ["dataset.subsample=2"]
else:  # without the shared data: a rendered sequence, used RGB-only all the same
    source, overrides = "synthetic:forward:40:128x96", []

cfg = load_config("twoview", overrides)
src = open_source(source, cfg, prior="twoview")
system, _ = run_slam(src, cfg, load_kernels("fast"))
seq = src.sequence
idx, ts, T = system.frame_poses()
print(f"{len(idx)} / {len(seq)} frames posed, {len(system.keyframes)} keyframes, "
      f"{system.graph.count('retrieval')} retrieval edges")  # fmt: skip
ate = evaluate.ate(ts, T, seq.timestamps, seq.T_WC)
print(f"ATE (Sim(3)) {ate.rmse * 100:.1f} cm")

# %% [markdown]
# ## The scale of each keyframe's pointmap
#
# A keyframe's pointmap `X_canon` lives in its camera at the scale of the pairs that made it;
# its pose `T_WC = (t, q, s)` carries it into the world with the factor `s`. So the world-frame
# size of keyframe k's geometry is `s_k · median(z_k)`, and against ground-truth depth
# (7-Scenes has it; the prior never read it) the ratio
# `r_k = s_k · median(z_k) / median(z_gt)` should be the same for every keyframe. We plot
# `r_k / r_0` with the pose from tracking alone (`T_WC_init`) and with the final pose.


# %%
def scale_ratio(kf, T_WC):
    """World-frame scale of keyframe ``kf``'s pointmap over ground truth (valid depth)."""
    z_gt = kf.frame.depth
    H, W = kf.shape
    z = kf.state.X_canon.reshape(H, W, 3)[..., 2]
    ok = (z_gt > 0) & (z > 0)
    return T_WC[7] * np.median(z[ok]) / np.median(z_gt[ok])


before = np.array([scale_ratio(kf, kf.T_WC_init) for kf in system.keyframes])
after = np.array([scale_ratio(kf, kf.T_WC) for kf in system.keyframes])
before, after = before / before[0], after / after[0]
for k, (b, a) in enumerate(zip(before, after)):
    print(f"keyframe {k:2d}: scale / keyframe 0 before {b:.3f}, after {a:.3f}")
spread = {name: float(np.std(np.log(r))) for name, r in (("before", before), ("after", after))}
print(f"std of log scale: before {spread['before']:.3f}, after {spread['after']:.3f}")
assert len(idx) >= 0.8 * len(seq)
assert spread["after"] < spread["before"]

# %%
fig, ax = plt.subplots(figsize=(7, 4))
kf_frames = [kf.frame.index for kf in system.keyframes]
ax.axhline(1.0, color="0.6", lw=2, label="ground truth (consistent scale)")
ax.plot(kf_frames, before, "o--", color="C1", label="tracking only (T_WC_init)")
ax.plot(kf_frames, after, "o-", color="C0", label="after backend + loop closure")
ax.set_xlabel("keyframe (frame index)")
ax.set_ylabel("pointmap scale / keyframe 0")
ax.set_title("per-keyframe scale, 7-Scenes redkitchen RGB only (twoview prior)")
ax.legend(fontsize=8)
fig.tight_layout()
out = Path(os.environ.get("MSLAM_TUTORIAL_OUT", "."))
fig.savefig(out / "07_keyframe_scale.png", dpi=100)
plt.close(fig)

# %% [markdown]
# What the plot shows (7-Scenes, measured 2026-11-25: std of log scale 0.99 with the creation
# poses, 0.31 with the final ones; benchmarks/RESULTS.md, "Two-view prior"):
#
# * **tracking alone** — every pair has its own arbitrary scale; Sim(3) tracking absorbs it
#   into the frame's pose, but each new keyframe inherits the error of the one pair that made
#   it, so keyframe scales jump by factors of 2–10 from one keyframe to the next;
# * **after the backend** — the Sim(3) edges between keyframes (consecutive and retrieval,
#   i.e. loop-closure, edges) tie each keyframe's scale to its neighbours' and the jumps
#   disappear. What remains is a slow drift along the sequence (monocular scale drift): a
#   loop back to the start would pin it, a short clip has only the local edges.
#
# With SE(3) poses the scale of each pair could only be absorbed by moving the cameras — the
# reason MASt3R-SLAM's poses, and this implementation's, are Sim(3).
