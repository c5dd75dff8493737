"""What keeps a run's cost from growing with the resolution and the map.

* patch descriptors built a few rows at a time equal the one-matrix formula;
* ICP and the backend use a regular pixel grid whose size does not grow with the image;
* a graph candidate that cannot pass the quality gate is rejected before matching, with the
  outcome matching would have given;
* the background backend (``single_thread: False``) gives a complete, accurate run.
"""

from __future__ import annotations

import dataclasses
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
from tolerances import DESCRIPTOR_FORMULA, F32_UNIT

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.priors.descriptors import DescriptorConfig, _projection, patch_descriptors
from mslam.priors.rgbd_pose import icp_sample
from mslam.system import open_source, run_slam
from mslam.system.edges import cannot_pass
from mslam.system.global_opt import residual_grid
from mslam.system.graph import FactorGraph
from mslam.system.outputs import evaluate_run
from mslam.system.worker import BackendWorker, SharedPrior


def _descriptors_one_matrix(rgb: np.ndarray, cfg: DescriptorConfig):
    """The defining formula with the whole (H·W, 3p²) patch matrix at once."""
    import cv2

    H, W = rgb.shape[:2]
    img = cv2.GaussianBlur(rgb / 255.0, (0, 0), cfg.blur_sigma, borderType=cv2.BORDER_REFLECT)
    r = (cfg.patch // 2) * cfg.step
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="reflect" if min(H, W) > r else "edge")
    win = sliding_window_view(pad, (2 * r + 1, 2 * r + 1), axis=(0, 1))
    z = win[..., :: cfg.step, :: cfg.step].transpose(0, 1, 3, 4, 2).reshape(H * W, -1)
    z = z - z.mean(axis=1, keepdims=True)
    contrast = np.sqrt((z * z).mean(axis=1))
    D = (z @ _projection(cfg)) / (contrast + cfg.eps)[:, None]
    D[:, 0] += 1e-6
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return D.reshape(H, W, -1), contrast.reshape(H, W)


@pytest.mark.parametrize("kind", ["dense", "separable"])
@pytest.mark.parametrize(("H", "W", "step"), [(37, 29, 1), (16, 40, 2), (3, 5, 1), (50, 33, 3)])
def test_patch_descriptors_equal_the_formula(H, W, step, kind) -> None:
    rng = np.random.default_rng(H * W + step)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    cfg = DescriptorConfig(kind=kind, step=step)
    D, c = patch_descriptors(rgb, cfg)
    D0, c0 = _descriptors_one_matrix(rgb, cfg)
    # The descriptors are float32 (the contrast is summed in float64 from float32 pixels).
    assert D.dtype == np.float32
    np.testing.assert_allclose(c, c0, atol=F32_UNIT)
    np.testing.assert_allclose(D, D0, atol=DESCRIPTOR_FORMULA)
    np.testing.assert_allclose(np.linalg.norm(D, axis=-1), 1.0, atol=F32_UNIT)


@pytest.mark.parametrize(("H", "W"), [(120, 160), (192, 256), (384, 512), (480, 640)])
def test_icp_sample_keeps_a_bounded_spread_grid(H, W) -> None:
    valid = np.ones((H, W), bool)
    valid[:, : W // 5] = False  # no depth on a strip
    n_points = 10_000
    m = icp_sample(valid, n_points)
    assert not (m & ~valid).any()
    if valid.sum() <= 2 * n_points:
        assert (m == valid).all()  # small images keep every valid pixel
    else:
        assert n_points <= m.sum() <= 4 * n_points
        rows, cols = np.nonzero(m)
        assert rows.min() < H // 8 and rows.max() > H - H // 8  # spread over the image
        assert cols.max() > W - W // 8


def test_residual_grid_and_stride_from_the_config() -> None:
    cfg = load_config("rgbd")
    budget = cfg.sections["local_opt"]["pixels_per_edge"]
    for H, W in [(120, 160), (192, 256), (384, 512)]:
        s = cfg.backend_pixel_stride((H, W))
        n = int(residual_grid((H, W), s).sum())
        assert n == len(range(s // 2, H, s)) * len(range(s // 2, W, s))
        assert budget / 2 < n < 2 * budget or s == 1
    assert load_config().backend_pixel_stride((384, 512)) == 1  # upstream: every pixel
    assert residual_grid((4, 6), 1).all()


class _FailingPrior:
    """Wraps a prior; pairs involving keyframe frame ``bad`` look like a failed pose."""

    def __init__(self, prior, bad: int) -> None:
        self.prior, self.bad, self.calls = prior, bad, 0

    def pair(self, fi, fj):
        self.calls += 1
        p = self.prior.pair(fi, fj)
        if self.bad in (fi.index, fj.index):
            p = dataclasses.replace(p, Q_ji=np.full_like(p.Q_ji, 0.01))
        return p


def test_doomed_candidates_are_rejected_before_matching(fast64) -> None:
    cfg = load_config()
    src = open_source("synthetic:loop:24:48x36", cfg)
    system, _ = run_slam(src, cfg, load_kernels("fast"))
    k = len(system.keyframes) - 1
    store = system.keyframes
    assert k >= 3
    bad = store[1].frame.index
    prior = _FailingPrior(system.prior, bad)
    bcfg = system.backend.backend_cfg
    builder = dataclasses.replace(system.backend.edges, prior=prior)
    ii, jj = [k - 1, 1, 0], [k, k, k]
    # What matching every candidate would decide.
    full = builder.match_pairs(ii, jj)
    expect = [e.i == e.j - 1 or e.match_frac >= bcfg.min_match_frac for e in full]
    assert expect[1] is False  # the failing candidate is rejected after matching
    prior.calls = 0
    g = FactorGraph()
    g.add_factors(builder, ii, jj, min_match_frac=bcfg.min_match_frac)
    assert [(e.i, e.j) for e in g.edges] == [(i, j) for i, j, x in zip(ii, jj, expect) if x]
    assert g.candidates_rejected_early == 1 and g.candidates_tested == 3
    assert prior.calls == 3 + 2  # forward decodes, then backward ones for the survivors only


def test_cannot_pass_is_the_quality_bound() -> None:
    p = SimpleNamespace(Q_ii=np.array([1.0, 4.0]), Q_ji=np.array([0.5, 0.5]))
    assert not cannot_pass(p, 1.0)  # sqrt(4 · 0.5) = 1.41 > 1
    assert cannot_pass(p, 1.5)


def test_background_backend_run_is_complete_and_accurate(fast64) -> None:
    source = "synthetic:loop:40:64x48"
    out = {}
    for single in (True, False):
        cfg = load_config(None, [f"single_thread={str(single).lower()}"])
        src = open_source(source, cfg)
        system, _ = run_slam(src, cfg, load_kernels("fast"))
        assert (system.worker is None) == single
        ev = evaluate_run(system, src.sequence)
        out[single] = (system, ev)
    sync, bg = out[True][0], out[False][0]
    assert len(bg.frame_poses()[0]) == len(sync.frame_poses()[0]) == 40
    assert bg.stats.backend_solves == len(bg.keyframes) - 1  # every keyframe got its solve
    assert bg.graph.count("retrieval") >= 1  # the loop still closes
    assert out[False][1]["ate_percent_of_path"] < 2 * max(out[True][1]["ate_percent_of_path"], 0.5)
    assert bg.worker is not None and not bg.worker.alive  # closed at the end of the run


def test_worker_errors_reach_the_frontend() -> None:
    def step(k, known):
        raise FloatingPointError(f"solve {k} diverged")

    w = BackendWorker(step)
    w.submit(3)
    with pytest.raises(RuntimeError, match="solve 3 diverged"):
        w.drain()
    w.close()
    with pytest.raises(RuntimeError, match="closed"):
        w.submit(4)


def test_shared_prior_keeps_the_status_of_each_thread() -> None:
    class Prior:
        last_status = "ok"
        K = "intrinsics"

        def pair(self, a, b):
            self.last_status = f"{a}-{b}"
            return a + b

    shared = SharedPrior(Prior())
    assert shared.pair(1, 2) == 3 and shared.last_status == "1-2" and shared.K == "intrinsics"
    seen = []
    t = threading.Thread(target=lambda: (shared.pair(5, 6), seen.append(shared.last_status)))
    t.start()
    t.join()
    assert seen == ["5-6"] and shared.last_status == "1-2"


def test_rgbd_budgets_give_the_grids_of_each_working_size() -> None:
    """rgbd.yaml's pixel budgets (nearest stride): tracking on every pixel at 160x120, stride 2
    at 256x192, 3 at 512x384; graph edges and the new-keyframe test's cells every pixel,
    stride 2, stride 4; one keyframe threshold at every size."""
    rgbd = load_config("rgbd")
    sizes = [(120, 160), (192, 256), (384, 512)]
    assert [rgbd.tracking_pixel_stride(s) for s in sizes] == [1, 2, 3]
    assert [rgbd.backend_pixel_stride(s) for s in sizes] == [1, 2, 4]
    # The new-keyframe test's cells: the tracking grid's at 160x120 and 256x192, 4x4 at 512x384.
    assert [rgbd.keyframe_cell_stride(s) for s in sizes] == [1, 2, 4]
    assert load_config().keyframe_cell_stride((384, 512)) == 1  # upstream: frame pixels
    assert rgbd.tracking().match_frac_thresh == load_config("rgbd_512").tracking().match_frac_thresh


def test_run_precision_option(tmp_path, capsys) -> None:
    import mslam_fast
    from mslam.cli import main

    try:
        out = tmp_path / "o"
        code = main(["run", "synthetic:loop:8:48x36", "--out", str(out), "--precision", "f32"])
        assert code == 0 and (out / "trajectory.txt").is_file()
        assert mslam_fast.current().fp == "f32"
        with pytest.raises(SystemExit) as exc:
            main(["run", "--out", str(tmp_path / "p"), "--precision", "f16"])
        assert exc.value.code == 2
    finally:
        mslam_fast.init("cpu", "f64")


@pytest.mark.parametrize(("H", "W", "stride"), [(48, 64, 2), (36, 48, 4), (37, 51, 3), (5, 7, 1)])
def test_grid_cells_number_the_grid_pixels_one_to_one(H, W, stride) -> None:
    from mslam.system.tracker import grid_cells as _grid_cells
    from mslam_ref.pointmap import strided_pixels

    g = np.flatnonzero(strided_pixels(H, W, stride))
    cells = _grid_cells(g, (H, W), stride)
    assert sorted(cells.tolist()) == list(range(len(g)))  # each grid pixel its own cell
    every = _grid_cells(np.arange(H * W), (H, W), stride)  # any frame pixel lands in a cell
    assert every.min() == 0 and every.max() == len(g) - 1


@pytest.mark.parametrize("calib", ["false", "true"])
def test_tracking_and_edges_on_pixel_grids_keep_the_run(fast64, calib: str) -> None:
    """Tracking on a stride-2 grid of keyframe pixels and graph edges matched on the backend's
    stride-2 grid: every frame posed, the loop closed, ATE close to matching every pixel
    (calibrated mode keeps the keyframe's layout and masks the pixels off the grid)."""
    source = "synthetic:loop:40:96x72"
    sets = {"all": [], "grid": ["tracking.pixels_per_frame=1728", "local_opt.pixels_per_edge=1728"]}
    out = {}
    for name, overrides in sets.items():
        cfg = load_config(None, [f"use_calib={calib}", *overrides])
        assert cfg.tracking_pixel_stride((72, 96)) == (2 if name == "grid" else 1)
        src = open_source(source, cfg)
        system, _ = run_slam(src, cfg, load_kernels("fast"))
        out[name] = (system, evaluate_run(system, src.sequence))
    system, ev = out["grid"]
    assert len(system.frame_poses()[0]) == 40
    assert system.graph.count("retrieval") >= 1
    assert ev["ate_percent_of_path"] < 2 * max(out["all"][1]["ate_percent_of_path"], 0.5)
