"""Videos unlike the ones the system was tuned on: the health checks hold on them.

* A camera walking steadily towards a wall (the synthetic ``forward`` path, which ends 1.6 m
  from the room's far wall): a prior that normalises its pointmaps (the two-view prior, MASt3R)
  gives keyframe Sim(3) scales that shrink with the scene's distance, steadily and by more than
  the spread watch's factor 2 over 8 keyframes. That is the walk, not a runaway map: the watch
  takes out the change that the keyframes' motion along their optical axes explains, and
  still reports the same scale change without that motion.
"""

from __future__ import annotations

import numpy as np

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
