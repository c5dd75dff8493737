"""The SLAM system end to end on short synthetic sequences (small images, few frames).

Runs are cached per (source, kernels, overrides) within the module so that several properties
share one run. Sizes are chosen to keep the module within ~1 minute on 2 cores.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import Mode, open_source, run_slam
from mslam.system.graph import FactorGraph
from mslam.system.keyframes import KeyframeStore
from mslam_ref import sim3

LOOP = "synthetic:loop:24:64x48"
JUMP = "synthetic:jump:32:64x48"
TINY = "synthetic:loop:10:48x36"  # small enough for the NumPy backend

_CACHE: dict = {}


def _run(source: str, kernels: str = "fast", overrides: tuple[str, ...] = ()):
    """One cached run; the fast kernel set runs in float64 (other tests may switch to f32)."""
    key = (source, kernels, overrides)
    if key not in _CACHE:
        if kernels == "fast":
            import mslam_fast

            mslam_fast.init("cpu", "f64")
        cfg = load_config(None, list(overrides))
        src = open_source(source, cfg)
        _CACHE[key] = (src, *run_slam(src, cfg, load_kernels(kernels)))
    return _CACHE[key]


def test_loop_creates_keyframes_and_tracks_every_frame():
    src, system, meta = _run(LOOP)
    n = len(src.sequence)
    assert system.stats.frames == n
    assert 3 <= len(system.keyframes) <= n
    idx, _ts, T = system.frame_poses()
    assert len(idx) == n and np.all(np.isfinite(T))
    assert system.stats.lost_frames == 0
    assert np.allclose(system.keyframes[0].T_WC, sim3.identity())  # gauge: first kf fixed
    assert system.mode == Mode.TERMINATED and not meta["interrupted"]


def test_loop_closes_the_loop():
    _, system, _ = _run(LOOP)
    loops = [e for e in system.graph.edges if e.kind == "retrieval"]
    assert loops, "no loop-closure edge accepted"
    K = len(system.keyframes)
    # an edge from one of the first keyframes to one of the last: the loop is closed
    assert any(e.i <= 2 and e.j >= K - 3 for e in loops)
    # every consecutive pair of keyframes is connected
    cons = {(e.i, e.j) for e in system.graph.edges if e.kind == "consecutive"}
    assert cons == {(k - 1, k) for k in range(1, K)}


def test_loop_trajectory_is_accurate():
    from mslam.system.outputs import evaluate_run

    src, system, _ = _run(LOOP)
    ev = evaluate_run(system, src.sequence)
    assert ev["ate"]["matched"] == len(src.sequence)
    # tiny images and few frames: a loose bound (the acceptance runs measure the real one)
    assert ev["ate"]["ate_rmse"] < 0.04 * ev["path_length"]


def test_run_is_deterministic():
    cfg = load_config()
    src = open_source(LOOP, cfg)
    _, system_a, _ = _run(LOOP)
    system_b, _ = run_slam(src, cfg, load_kernels("fast"))
    Ta, Tb = system_a.frame_poses()[2], system_b.frame_poses()[2]
    assert np.array_equal(Ta, Tb)
    assert [(e.i, e.j) for e in system_a.graph.edges] == [(e.i, e.j) for e in system_b.graph.edges]


def test_frames_run_with_one_blas_thread():
    """``SlamSystem.process`` runs each frame with single-threaded BLAS and gives the caller's
    setting back (two spinning OpenBLAS threads took the cores from Taichi and OpenCV)."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from mslam.system.frontend import SlamSystem

    def blas_threads() -> int:
        return max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    cfg = load_config()
    src = open_source(TINY, cfg)
    seen, mono = [], src.prior.mono
    src.prior.mono = lambda frame: (seen.append(blas_threads()), mono(frame))[1]
    system = SlamSystem(src.prior, cfg, load_kernels("fast"), src.K)
    with threadpool_limits(limits=2, user_api="blas"):
        assert system.process(src.sequence[0]) == "keyframe"
        after = blas_threads()
    assert seen == [1] and after == 2


def test_jump_relocalises_and_finishes():
    from mslam.system.outputs import evaluate_run
    from mslam_ref.synthetic import jump_indices

    src, system, _ = _run(JUMP)
    n = len(src.sequence)
    (j,) = jump_indices(n)
    assert system.stats.frames == n
    assert system.poses[j].status == "lost"  # the kidnap: nothing of the last keyframe in view
    assert all(p.status != "lost" for p in system.poses[:j])
    reloc = [p for p in system.poses if p.status == "relocalised"]
    assert reloc and j < reloc[0].index <= j + 5  # back on the mapped arc within five frames
    assert system.stats.relocalisations == 1
    assert any(e.kind == "reloc" for e in system.graph.edges)
    assert system.poses[-1].status != "lost"
    assert len(system.frame_poses()[0]) >= 0.9 * n
    ev = evaluate_run(system, src.sequence)
    assert ev["ate"]["ate_rmse"] < 0.05 * ev["path_length"]


def test_tracking_that_never_recovers_ends_cleanly():
    # The strictest tracking threshold (every pixel must match): every frame after the first is
    # lost. No new map (mslam.system.recovery): the run stays lost, as upstream.
    no_new_map = ("recovery.max_lost_frames=0", "recovery.max_refusals=0")
    src, system, _meta = _run(LOOP, overrides=("tracking.min_match_frac=1.0", *no_new_map))
    assert system.stats.frames == len(src.sequence)
    assert len(system.keyframes) >= 1
    assert system.stats.lost_frames + system.stats.relocalisations == len(src.sequence) - 1
    assert system.stats.lost_frames >= 1
    assert len(system.frame_poses()[0]) == 1 + system.stats.relocalisations


def test_fast_and_ref_agree():
    # Never skipped: the fast kernel set is made of mslam_fast modules only (no fallback exists).
    assert all(
        getattr(load_kernels("fast"), piece).__name__.startswith("mslam_fast.")
        for piece in ("matching", "tracking", "fusion", "backend")
    )
    _, ref, _ = _run(TINY, "ref")
    _, fast, _ = _run(TINY, "fast")
    assert len(fast.keyframes) == len(ref.keyframes)
    assert [(e.i, e.j) for e in fast.graph.edges] == [(e.i, e.j) for e in ref.graph.edges]
    Tr, Tf = ref.frame_poses()[2], fast.frame_poses()[2]
    assert np.max(np.linalg.norm(Tr[:, :3] - Tf[:, :3], axis=1)) < 1e-4


def test_keyframe_store_grows_and_graph_blocks():
    store = KeyframeStore()
    assert len(store) == 0 and store.poses().shape == (0, 8)
    graph = FactorGraph()
    blocks = graph.two_way_blocks()
    assert blocks.ii.shape == (0,)
    _, system, _ = _run(LOOP)
    b = system.graph.two_way_blocks()
    E = len(system.graph)
    assert b.idx.shape == (2 * E, 64 * 48) and b.valid.dtype == bool
    e = system.graph.edges[0]
    # block (i <- j) then (j <- i)
    assert (b.ii[0], b.jj[0]) == (e.i, e.j) and (b.ii[E], b.jj[E]) == (e.j, e.i)
    assert np.array_equal(b.idx[E], e.idx_j2i)


def test_calibrated_mode_runs():
    src, system, _ = _run("synthetic:loop:12:64x48", overrides=("use_calib=true",))
    assert system.K is not None
    idx, _, T = system.frame_poses()
    assert len(idx) == len(src.sequence) and np.all(np.isfinite(T))


def test_ref_run_never_imports_taichi():
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from mslam.cli import main\n"
        "rc = main(['run', 'synthetic:loop:40:48x36', '--out', sys.argv[1], '--kernels', 'ref',"
        " '--max-frames', '4', '--quiet'])\n"
        "assert rc == 0, rc\n"
        "assert 'taichi' not in sys.modules and 'mslam_fast' not in sys.modules\n"
    )
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        res = subprocess.run([sys.executable, "-c", code, tmp], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]


def test_rgbd_resolution_presets_are_rgbd_at_their_size():
    """``rgbd_256.yaml`` / ``rgbd_512.yaml`` (docs/system.md "One configuration, every
    resolution"): rgbd.yaml with ``dataset.long_side`` set, nothing else, so ``--config rgbd_512``
    and ``--set dataset.long_side=512`` are the same run."""
    from mslam.config import config_to_dict

    rgbd = config_to_dict(load_config("rgbd"))
    for size in (256, 512):
        preset = config_to_dict(load_config(f"rgbd_{size}"))
        assert preset == config_to_dict(load_config("rgbd", [f"dataset.long_side={size}"]))
        assert preset["dataset"]["long_side"] == size
        preset["dataset"]["long_side"] = rgbd["dataset"]["long_side"]
        assert preset == rgbd


def test_rgbd_config_is_base_with_documented_changes():
    """``configs/rgbd.yaml`` (docs/system.md): base.yaml except fusion mode, keyframe threshold,
    dilation rounds, the work budgets, the solve window, the metric distance error and the
    working resolution."""
    base, rgbd = load_config(), load_config("rgbd")
    assert rgbd.tracking().match_frac_thresh == 0.5
    assert rgbd.fusion().filtering_mode == "first"
    assert base.fusion().filtering_mode == "weighted_pointmap"
    assert base.tracking().match_frac_thresh == pytest.approx(0.333)
    assert rgbd.backend() == replace(base.backend(), window_size=16, sigma_dist=0.01)
    assert base.backend().sigma_dist == base.tracking().sigma_dist == 10  # upstream's
    assert rgbd.tracking().sigma_dist == 0.01
    assert rgbd.tracking().sigma_depth == base.tracking().sigma_depth
    assert base.backend().window_size >= 1e6  # upstream: the whole graph
    assert rgbd.matching() == replace(base.matching(), dilation_max=2)
    assert rgbd.use_calib == base.use_calib
    assert rgbd.dataset.long_side == 160 and base.dataset.long_side == 0
    assert rgbd.dataset.subsample == base.dataset.subsample
