"""Videos unlike the ones the system was tuned on: the health checks hold on them.

* A camera walking steadily towards a wall (the synthetic ``forward`` path, which ends 1.6 m
  from the room's far wall): a prior that normalises its pointmaps (the two-view prior, MASt3R)
  gives keyframe Sim(3) scales that shrink with the scene's distance, steadily and by more than
  the spread watch's factor 2 over 8 keyframes. That is the walk, not a runaway map: the watch
  takes out the change that the keyframes' motion along their optical axes explains, and
  still reports the same scale change without that motion. The whole RGB-only system on the
  walk (160x120, 40 frames, 11 keyframes) reports no spread.
* A camera at rest at the start (identical images): the frames wait for the first pair with
  parallax and are posed, instead of each restarting the wait and staying unposed; the first
  step after the rest is no jump for the divergence watch.
* A covered lens (black frames): lost, but blank, so they do not count towards a new map.
"""

from __future__ import annotations

import numpy as np
from blind_prior import BlindPrior

from mslam.system.divergence import DivergenceConfig, map_spread
from mslam_ref.pointmap import backproject
from mslam_ref.synthetic import camera_path, intrinsics, make_scene, render

N_KF = 12  # keyframes along the walk
W, H = 32, 24  # rendering size for the scene's distances


def _walk_to_the_wall() -> tuple[np.ndarray, np.ndarray]:
    """Keyframe poses (N_KF, 8) along the forward walk with the Sim(3) scale a normalising
    prior gives (the median distance of the rendered scene), and those distances (N_KF,)."""
    T = camera_path("forward", N_KF, 0)
    K, scene = intrinsics(W, H, 70.0), make_scene(0)
    dist = np.array(
        [
            np.median(np.linalg.norm(backproject(render(scene, t, K, W, H)[1], K), axis=-1))
            for t in T
        ]
    )
    T = T.copy()
    T[:, 7] = dist
    return T, dist


def test_the_spread_watch_accepts_a_camera_walking_towards_a_wall() -> None:
    T, dist = _walk_to_the_wall()
    cfg = DivergenceConfig()
    w = cfg.spread_window
    assert dist[-1] < dist[-w - 1] / cfg.max_scale_drift  # the scene's distance halves, steadily
    assert np.all(np.diff(dist) < 0)
    normalised = np.ones(N_KF)  # the canonical pointmaps' median distance
    assert map_spread(T, cfg, normalised) is None
    assert map_spread(T[::-1], cfg, normalised) is None  # walking away: the scale grows
    # Without the depths the same scales read as a drift ...
    assert "scale shrank" in map_spread(T, cfg)
    # ... and with them, the same scales on a camera that does not approach the scene do too.
    sideways = T.copy()
    sideways[:, :3] = T[0, :3] + np.outer(np.arange(N_KF), [0.0, 0.0, 0.3])  # up, not ahead
    assert "scale shrank" in map_spread(sideways, cfg, normalised)
    # A prior with metric pointmaps keeps the scale and carries the distances itself.
    metric = T.copy()
    metric[:, 7] = 1.0
    assert map_spread(metric, cfg, dist) is None


STILL = 5  # frames of the camera at rest at the start
MOVING = 6  # frames after it


def test_a_camera_at_rest_at_the_start_is_posed_not_lost() -> None:
    """The same image ``STILL`` times (a camera at rest, a video encoder repeating a frame),
    then the forward walk: the two-view prior cannot match a pair of identical images, yet the
    frames at rest wait for the first pair with parallax and are posed with the view they show
    (keyframe 0's)."""
    import dataclasses

    from mslam.config import load_config
    from mslam.datasets.synthetic import make_sequence
    from mslam.kernels import load_kernels
    from mslam.priors.twoview import TwoViewPrior
    from mslam.system.frontend import SlamSystem

    seq = make_sequence("forward", n_frames=40, width=128, height=96, seed=0)
    frames = [seq[0]] * STILL + [seq[i] for i in range(1, MOVING + 1)]
    frames = [dataclasses.replace(f, index=k) for k, f in enumerate(frames)]
    system = SlamSystem(TwoViewPrior(), load_config("twoview"), load_kernels("ref"))
    statuses = [system.process(f) for f in frames]
    assert statuses[:STILL] == ["waiting"] * STILL and "keyframe" in statuses
    idx, _, T = system.frame_poses()
    assert set(range(STILL)) <= set(idx.tolist())
    assert system.keyframes[0].frame.index == 0
    # Each frame at rest is where keyframe 0 is, far closer to it than to keyframe 1.
    c0, c1 = system.keyframes[0].T_WC[:3], system.keyframes[1].T_WC[:3]
    still = T[np.isin(idx, range(STILL)), :3]
    assert np.all(np.linalg.norm(still - c0, axis=1) < np.linalg.norm(still - c1, axis=1))


def test_blank_lost_frames_do_not_start_a_new_map() -> None:
    """Lost frames far darker and flatter than the posed ones (a covered lens) neither count
    towards ``max_lost_frames`` nor break a run of informative lost frames."""
    from mslam.system.recovery import Recovery, RecoveryConfig, frame_contrast
    from mslam.system.state import FrameStatus

    rng = np.random.default_rng(0)
    scene = rng.integers(0, 256, (24, 32, 3)).astype(np.uint8)
    dark = rng.normal(4.0, 2.0, (24, 32, 3)).clip(0, 255).astype(np.uint8)
    c_scene, c_dark = frame_contrast(scene), frame_contrast(dark)
    rec = Recovery(RecoveryConfig(max_lost_frames=3))
    lost, tracked = FrameStatus.LOST, FrameStatus.TRACKED
    assert rec.after_frame(0, lost, [], c_dark) is None  # no posed frame yet: counts
    assert rec.after_frame(1, tracked, [], c_scene) is None
    assert all(rec.after_frame(i, lost, [], c_dark) is None for i in range(2, 40))
    assert rec.blank_frames == 38
    assert rec.after_frame(40, lost, [], c_scene) is None
    assert rec.after_frame(41, lost, [], c_dark) is None  # blank: the run goes on ...
    assert rec.after_frame(42, lost, [], c_scene) is None
    assert "3 consecutive frames lost" in rec.after_frame(43, lost, [], c_scene)  # ... to 3


DARK = range(24, 30)  # frames of the synthetic loop behind a covered lens
MAX_LOST = 4  # recovery.max_lost_frames of that run


def test_a_covered_lens_does_not_start_a_new_map() -> None:
    """Six black frames (sensor noise only) that nothing can be matched in: tracking is lost
    for all of them, more than ``recovery.max_lost_frames``, yet they are blank, so no new map
    is started during them; one starts only after ``max_lost_frames`` informative frames have
    failed to relocalise too (on this 64x48 loop they do), and the blank frames are counted."""
    import dataclasses

    import mslam_fast
    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.system import open_source
    from mslam.system.frontend import SlamSystem

    mslam_fast.init("cpu", "f64")
    cfg = load_config(None, [f"recovery.max_lost_frames={MAX_LOST}"])
    src = open_source("synthetic:loop:96:64x48", cfg)
    rng = np.random.default_rng(0)
    system = SlamSystem(BlindPrior(src.prior, DARK), cfg, load_kernels("fast"), src.K)
    statuses = []
    for i in range(DARK.stop + 2 * MAX_LOST):
        f = src.sequence[i]
        if i in DARK:
            noise = rng.normal(4.0, 2.0, f.rgb.shape).clip(0, 255).astype(np.uint8)
            f = dataclasses.replace(f, rgb=noise)
        statuses.append(system.process(f))
    assert all(statuses[i] == "lost" for i in DARK) and len(DARK) > MAX_LOST
    assert system.recovery.blank_frames == len(DARK)
    starts = [m["first_frame"] for m in system.recovery.maps[1:]]
    assert all(f >= DARK.stop + MAX_LOST - 1 for f in starts), starts


def test_a_camera_starting_to_move_after_rest_is_no_jump() -> None:
    """Twenty frames at rest (steps of 1e-4, tracking noise), then steps of 3 mm at scale 1:
    the first moving step is 30 median steps but a small share of the scale, so neither the
    monitor nor the final-trajectory check calls it a jump; a step of half the scale is one."""
    from mslam.system.divergence import DivergenceMonitor, trajectory_warnings

    rng = np.random.default_rng(0)
    x = np.concatenate([1e-4 * rng.standard_normal(20), 0.003 * np.arange(1, 81)])
    T = np.zeros((len(x), 8))
    T[:, 0], T[:, 6], T[:, 7] = x, 1.0, 1.0
    mon = DivergenceMonitor()
    assert all(mon.check(k, t) for k, t in enumerate(T)) and mon.events == []
    assert trajectory_warnings(T) == []
    jump = T.copy()
    jump[60:, 0] += 0.5
    assert any("jumps" in w for w in trajectory_warnings(jump))
    mon2 = DivergenceMonitor()
    assert all(mon2.check(k, t) for k, t in enumerate(T[:60]))
    assert not mon2.check(60, jump[60])


WALK = "synthetic:forward:40:160x120"  # 3 m towards the far wall, ending 1.6 m from it


def test_the_spread_watch_stays_silent_on_a_run_walking_towards_a_wall() -> None:
    """The whole RGB-only system on the walk (two-view prior, a keyframe at 60 % matched
    pixels so that the walk makes more than ``spread_window`` keyframes): the keyframes' scale
    shrinks by more than the watch's factor over its window, yet no spread is reported."""
    import mslam_fast
    from mslam.config import load_config
    from mslam.kernels import load_kernels
    from mslam.system import open_source, run_slam
    from mslam.system.outputs import evaluate_run, summary_dict

    mslam_fast.init("cpu", "f64")
    cfg = load_config("twoview", ["tracking.match_frac_thresh=0.6"])
    src = open_source(WALK, cfg, prior="twoview")
    system, meta = run_slam(src, cfg, load_kernels("fast"))
    s = summary_dict(system, meta, evaluate_run(system, src.sequence))
    T_kf = system.keyframes.poses()
    w = DivergenceConfig().spread_window
    assert len(T_kf) > w
    assert T_kf[-1, 7] < T_kf[-w - 1, 7] / DivergenceConfig().max_scale_drift
    assert "scale shrank" in map_spread(T_kf)  # what the watch saw without the motion
    assert [e for e in s["divergence_events"] if e["kind"] == "spread"] == []
    assert s["plausible"], s["warnings"]
