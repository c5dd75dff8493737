"""A run that goes wrong says so: the divergence watch, the backend guard, loop-closure
verification, and the summary's warnings.

The system is driven into divergence by a prior that, from frame ``CORRUPT_FROM`` on, returns
pointmaps blown up by a random factor per pair; the run must refuse those poses, say so in
``summary.json`` (``warnings``, ``plausible: false``, ``divergence_events``) and keep a finite
trajectory.
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import SIM3_FIT

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.divergence import (
    DivergenceConfig,
    DivergenceMonitor,
    divergence_report,
    guard_backend,
    trajectory_warnings,
)
from mslam.system.loop_verify import LoopVerifyConfig, fit_sim3_ransac
from mslam.system.outputs import evaluate_run, summary_dict
from mslam_ref import sim3, so3

LOOP = "synthetic:loop:24:64x48"
CORRUPT_FROM = 12


def _pose(x: float, s: float = 1.0) -> np.ndarray:
    return np.array([x, 0, 0, 0, 0, 0, 1, s], dtype=np.float64)


def test_monitor_refuses_jumps_and_scale_changes_and_non_finite_poses() -> None:
    mon = DivergenceMonitor()
    for k in range(10):
        assert mon.check(k, _pose(0.01 * k))
    assert not mon.check(10, _pose(1e3))  # 1e5 recent steps in one frame
    assert not mon.check(11, _pose(0.1, s=1e3))  # scale x1000 in one frame
    assert not mon.check(12, _pose(np.nan))
    assert mon.check(13, _pose(0.1))  # normal motion is accepted again
    assert [e["frame"] for e in mon.events] == [10, 11, 12]
    assert "3 implausible frame pose(s)" in mon.warnings()[0]
    assert DivergenceMonitor(events=mon.events[:1]).warnings() == []  # one recovered refusal


def test_guard_undoes_rising_cost_and_runaway_keyframes() -> None:
    T_old = np.stack([_pose(0.1 * k) for k in range(5)])
    cfg = DivergenceConfig()
    assert guard_backend(T_old, T_old + 1e-4, (2.0, 1.0, 0.5), cfg) is None
    assert "cost rose" in guard_backend(T_old, T_old, (1.0, 5.0), cfg)
    far = T_old.copy()
    far[3, 0] = 1e6
    assert "keyframe spacings" in guard_backend(T_old, far, (1.0, 0.5), cfg)
    far[3, 0] = np.inf
    assert "non-finite" in guard_backend(T_old, far, (1.0, 0.5), cfg)
    # A rise of 0.15 % is undone but minor (within warn_cost_rise); a fivefold one is not.
    slight = (1.0, 1.0015)
    assert "cost rose" in guard_backend(T_old, T_old, slight, cfg)
    assert guard_backend(T_old, T_old, slight, cfg, cfg.warn_cost_rise) is None
    assert guard_backend(T_old, T_old, (1.0, 5.0), cfg, cfg.warn_cost_rise) is not None


def test_a_minor_undone_solve_is_listed_but_not_warned() -> None:
    minor = {"frame": -1, "kind": "solve", "reason": "backend undone: cost rose", "minor": True}
    assert DivergenceMonitor(events=[minor]).warnings() == []
    assert DivergenceMonitor(events=[{**minor, "minor": False}]).warnings() != []
    report = divergence_report(DivergenceMonitor(events=[minor]), [], np.zeros((0, 8)), [])
    assert report["plausible"] and report["divergence_events"] == [minor]


def test_trajectory_warnings_flag_a_runaway_path() -> None:
    smooth = np.stack([_pose(0.01 * k) for k in range(100)])
    assert trajectory_warnings(smooth) == []
    runaway = smooth.copy()
    runaway[60:, 0] = 0.6 + 3.0 ** np.arange(40)  # 1e19 at the end, as a diverging run
    assert any("jumps" in w for w in trajectory_warnings(runaway))


def test_a_cut_is_a_jump_unless_a_merge_placed_the_frames_after_it() -> None:
    """A video cut: frames 0-74 walk one way, 90-149 continue 3 m away after 15 unposed
    frames. Unmerged, that step is a jump; when the map started at frame 80 was merged into the
    earlier one (its positions placed by verified connections) it is not, but a jump elsewhere
    still is."""
    idx = np.r_[0:75, 90:150]
    T = np.stack([_pose(0.01 * k + (3.0 if k >= 90 else 0.0)) for k in idx])
    maps = {"maps": [{"first_frame": None, "merged": None}, {"first_frame": 80, "merged": {}}]}
    assert any("between frames 74 and 90" in w for w in trajectory_warnings(T, idx=idx))
    assert trajectory_warnings(T, idx=idx, joined=[80]) == []
    assert divergence_report(DivergenceMonitor(), [], T, [], idx=idx, maps=maps)["plausible"]
    unmerged = {"maps": [maps["maps"][0], {"first_frame": 80, "merged": None}]}
    assert not divergence_report(DivergenceMonitor(), [], T, [], idx=idx, maps=unmerged)[
        "plausible"
    ]
    T[idx >= 120, 0] += 3.0  # a second jump, inside the merged map
    assert any(
        "between frames 119 and 120" in w for w in trajectory_warnings(T, idx=idx, joined=[80])
    )


def test_a_camera_at_rest_first_does_not_shrink_the_median_step() -> None:
    """30 frames at rest (0.3 mm jitter; most of the first quarter) before 120 frames of 6 mm
    steps: a 5 cm step near the end is 9 median steps, no jump; a 2 m step is one."""
    rng = np.random.default_rng(0)
    x = np.r_[np.cumsum(rng.uniform(-3e-4, 3e-4, 30)), np.linspace(0, 0.72, 120)]
    x[140:] += 0.05
    T = np.stack([_pose(v) for v in x])
    assert trajectory_warnings(T) == []
    x[140:] += 2.0
    assert any("jumps" in w for w in trajectory_warnings(np.stack([_pose(v) for v in x])))


def test_trajectory_warnings_flag_an_orientation_that_jumps() -> None:
    """A camera turning 3.8° per frame about its centre (``synthetic:rotation:60``'s rate):
    no warning, with or without lost frames; frames of a keyframe 40° off, tracked in turns
    with frames of its neighbour, make the orientation jump back and forth: a warning."""
    k = np.arange(60)
    T = np.zeros((60, 8))
    T[:, 3:7] = so3.exp(np.radians(3.8) * k[:, None] * np.array([0.0, 1.0, 0.0]))
    T[:, 7] = 1.0
    assert trajectory_warnings(T, idx=k) == []
    kidnap = T.copy()
    kidnap[45:, 3:7] = so3.mul(kidnap[45:, 3:7], so3.exp(np.radians([90.0, 0.0, 0.0])))
    kept = np.r_[0:30, 45:60]  # 15 frames without a pose: a turn across them is no jump
    assert trajectory_warnings(kidnap[kept], idx=k[kept]) == []
    wrong = T.copy()
    off = so3.exp(np.radians(40.0) * np.array([1.0, 0.0, 0.0]))
    wrong[40::2, 3:7] = so3.mul(wrong[40::2, 3:7], off)
    assert trajectory_warnings(wrong) == []  # without frame indices the test does not run
    assert any("orientation jumps" in w for w in trajectory_warnings(wrong, idx=k))
    assert not divergence_report(DivergenceMonitor(), [], wrong, [], idx=k)["plausible"]
    assert divergence_report(DivergenceMonitor(), [], T, [], idx=k)["plausible"]


def test_sim3_ransac_finds_the_similarity_despite_outliers() -> None:
    rng = np.random.default_rng(1)
    centre = np.array([0.0, 0.0, 4.0])
    src = rng.normal(size=(400, 3)) + centre
    T = sim3.exp(np.array([0.2, -0.1, 0.3, 0.05, 0.1, -0.2, 0.4]))
    dst = sim3.act(T, src)
    dst[:120] = rng.normal(size=(120, 3)) * 3 + centre  # 30 % wrong matches
    R, t, s, inl = fit_sim3_ransac(src, dst, LoopVerifyConfig())
    np.testing.assert_allclose(s * src[150] @ R.T + t, dst[150], atol=SIM3_FIT)
    assert inl[120:].mean() > 0.99 and inl[:120].mean() < 0.1
    np.testing.assert_allclose(s, T[7], rtol=SIM3_FIT)
    # Unrelated points: no similarity explains more than a few of them.
    _, _, _, inl_bad = fit_sim3_ransac(src, rng.normal(size=(400, 3)) * 3, LoopVerifyConfig())
    assert inl_bad.mean() < LoopVerifyConfig().min_inlier_frac


class _CorruptedPrior:
    """Wraps a prior; from frame ``start`` on both pointmaps of every pair are shifted by one
    random vector ~30 scene depths long (a prior gone wild: the two pointmaps still agree, so
    matching and tracking succeed, and the camera jumps)."""

    def __init__(self, prior, start: int) -> None:
        self._p, self._start, self._rng = prior, start, np.random.default_rng(0)

    def __getattr__(self, name):
        return getattr(self._p, name)

    def mono(self, frame):
        return self._p.mono(frame)

    def pair(self, frame_i, frame_j):
        p = self._p.pair(frame_i, frame_j)
        if max(frame_i.index, frame_j.index) < self._start:
            return p
        d = self._rng.normal(size=3) * 30.0 * np.median(np.linalg.norm(p.X_ii, axis=-1))
        return type(p)(p.X_ii + d, p.C_ii, p.D_ii, p.Q_ii,
                       p.X_ji + d, p.C_ji, p.D_ji, p.Q_ji)  # fmt: skip


@pytest.fixture(scope="module")
def corrupted_run():
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    cfg = load_config(None)
    src = open_source(LOOP, cfg)
    src.prior = _CorruptedPrior(src.prior, CORRUPT_FROM)
    system, meta = run_slam(src, cfg, load_kernels("fast"))
    ev = evaluate_run(system, src.sequence)
    return system, summary_dict(system, meta, ev)


def test_corrupted_prior_is_reported_and_the_trajectory_stays_finite(corrupted_run) -> None:
    system, s = corrupted_run
    assert not s["plausible"] and s["warnings"]  # lost from CORRUPT_FROM on, never recovered
    assert s["divergence_events"], "the watch refused nothing"
    assert min(e["frame"] for e in s["divergence_events"] if e["frame"] >= 0) >= CORRUPT_FROM
    _, _, T = system.frame_poses()
    assert np.all(np.isfinite(T))
    steps = np.linalg.norm(np.diff(T[:, :3], axis=0), axis=1)
    assert steps.max() < DivergenceConfig().max_final_jump * max(np.median(steps), 1e-9) or any(
        "jumps" in w for w in s["warnings"]
    )
