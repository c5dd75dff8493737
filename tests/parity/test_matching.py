"""mslam_fast.matching against mslam_ref.matching: ray image, LM, refinement and ``match``.

Integer outputs are compared as the share of pixels on which both agree (``SHARE`` in
tests/tolerances.py). At float64 the only disagreements come from the last bits: LLVM fuses
multiply-adds and sums the descriptor dot products in vector lanes, so (a) an LM position that
ends within ~1e-15 px of an integer can truncate to either side, (b) a convergence or
distance test that sits on its threshold can flip, (c) two refinement candidates whose scores
tie to ~1e-16 can resolve differently. At float32 the same happens at ~1e-7 relative.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tolerances import SHARE, tol

from mslam_ref import matching as ref
from mslam_ref import sim3
from mslam_ref.pointmap import backproject

HAVE_PRIOR = importlib.util.find_spec("mslam.priors.synthetic") is not None
NO_REFINE = ref.MatchingConfig(radius=0)


def analytic_pair(W: int = 64, H: int = 48, seed: int = 0, F: int = 24):
    """A wavy surface seen from two nearby cameras (X21 = T_12 · X22 of the same surface is
    approximated by moving camera-1 points), descriptors a random Fourier feature of 3-D."""
    rng = np.random.default_rng(seed)
    K = np.array([[0.9 * W, 0.0, (W - 1) / 2], [0.0, 0.9 * W, (H - 1) / 2], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:H, 0:W]
    X11 = backproject(2.0 + 0.3 * np.sin(u / 9.0 + seed) + 0.2 * np.cos(v / 7.0), K)
    T = sim3.exp(np.concatenate([rng.normal(0, 0.03, 3), rng.normal(0, 0.02, 3), [0.0]]))
    X21 = sim3.act(T, X11) + rng.normal(0, 0.002, X11.shape)
    Om, ph = rng.normal(0, 20.0, (F, 3)), rng.uniform(0, 2 * np.pi, F)

    def desc(X):
        D = np.sin(X @ Om.T + ph)
        return D / np.linalg.norm(D, axis=-1, keepdims=True)

    return X11, X21, desc(X11), desc(X21)


def prior_pair(W: int = 96, H: int = 72, j: int = 1, seed: int = 0):
    """A noisy MASt3R-like pair from the synthetic prior (depth noise, outliers, Sim(3) error)."""
    from mslam.datasets.synthetic import make_sequence
    from mslam.priors.synthetic import SyntheticPrior, SyntheticPriorConfig

    seq = make_sequence("loop", n_frames=40, width=W, height=H, seed=0)
    P = SyntheticPrior(seq, SyntheticPriorConfig(seed=seed)).pair(seq[0], seq[j])
    return P.X_ii, P.X_ji, P.D_ii, P.D_ji


def _pairs():
    yield "analytic", analytic_pair()
    if HAVE_PRIOR:
        yield "prior-near", prior_pair(j=1)
        yield "prior-far", prior_pair(j=3)


PAIRS = dict(_pairs())


def _share(a: np.ndarray, b: np.ndarray) -> float:
    eq = a == b
    return float(np.mean(eq.all(axis=-1) if eq.ndim > 1 and a.shape[-1] == 2 else eq))


def _assert_share(a, b, fp: str, what: str) -> None:
    s = _share(a, b)
    assert s >= SHARE[("matching", fp)], f"{what}: fast and reference agree on {s:.5f} only"


# --- stages ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(PAIRS))
def test_ray_image_parity(fast: str, name: str) -> None:
    from mslam_fast import matching as fm

    X11 = PAIRS[name][0].copy()
    X11[1, 2] = 0.0
    X11[3, 4] = np.nan
    want = ref.ray_image_and_gradients(X11)
    got = fm.ray_image_and_gradients(X11)
    assert got.shape == want.shape and np.isfinite(got).all()
    np.testing.assert_allclose(got, want, **tol("matching", fast))
    got_b = fm.ray_image_and_gradients(np.stack([X11, X11]))
    np.testing.assert_array_equal(got_b[1], got)
    assert fm.ray_image_and_gradients(np.zeros((0, 5, 6, 3))).shape == (0, 5, 6, 9)


@pytest.mark.parametrize("name", list(PAIRS))
def test_iter_proj_parity(fast: str, name: str) -> None:
    from mslam_fast import matching as fm

    X11, X21 = PAIRS[name][:2]
    H, W = X11.shape[:2]
    rng = np.random.default_rng(0)
    n = np.arange(H * W)
    p0 = np.stack([n % W, n // W], -1) + rng.uniform(-3, 3, (H * W, 2))
    RG = ref.ray_image_and_gradients(X11)
    p_r, c_r = ref.iter_proj(RG, X21.reshape(-1, 3), p0)
    p_f, c_f = fm.iter_proj(RG, X21.reshape(-1, 3), p0)
    assert p_f.shape == p_r.shape and c_f.shape == c_r.shape and c_f.dtype == np.bool_
    _assert_share(np.floor(p_f), np.floor(p_r), fast, "iter_proj truncated positions")
    _assert_share(c_f, c_r, fast, "iter_proj convergence")
    close = np.all(np.abs(p_f - p_r) < (1e-9 if fast == "f64" else 1e-2), axis=-1)
    assert close.mean() >= SHARE[("matching", fast)]


@pytest.mark.parametrize("name", list(PAIRS))
def test_refine_matches_parity(fast: str, name: str) -> None:
    from mslam_fast import matching as fm

    X11, X21, D11, D21 = PAIRS[name]
    H, W, F = D11.shape
    n = np.arange(H * W)
    p, _ = ref.iter_proj(
        ref.ray_image_and_gradients(X11),
        X21.reshape(-1, 3),
        np.stack([n % W, n // W], -1).astype(float),
    )
    p1 = p.astype(np.int64)
    for cfg in (ref.MatchingConfig(), ref.MatchingConfig(radius=2, dilation_max=3)):
        want = ref.refine_matches(D11, D21.reshape(-1, F), p1, cfg)
        got = fm.refine_matches(D11, D21.reshape(-1, F), p1, cfg)
        assert got.dtype == np.int64 and got.shape == want.shape
        _assert_share(got, want, fast, f"refine_matches radius={cfg.radius}")


# --- end to end ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(PAIRS))
@pytest.mark.parametrize("radius", [0, 3])
def test_match_parity(fast: str, name: str, radius: int) -> None:
    from mslam_fast import matching as fm

    cfg = ref.MatchingConfig(radius=radius)
    i_r, v_r = ref.match(*PAIRS[name], cfg=cfg)
    i_f, v_f = fm.match(*PAIRS[name], cfg=cfg)
    assert i_f.dtype == np.int64 and v_f.dtype == np.bool_ and i_f.shape == i_r.shape
    _assert_share(i_f, i_r, fast, "match idx")
    _assert_share(v_f, v_r, fast, "match valid")


@settings(suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture])  # fmt: skip
@given(seed=st.integers(0, 2**16), offset=st.integers(-4, 4))
def test_match_parity_with_idx_init(fast: str, seed: int, offset: int) -> None:
    from mslam_fast import matching as fm

    X11, X21, D11, D21 = analytic_pair(48, 36, seed=seed)
    N = 48 * 36
    idx0 = np.clip(np.arange(N) + offset * (1 + 48), 0, N - 1)
    i_r, v_r = ref.match(X11, X21, D11, D21, idx_init=idx0)
    i_f, v_f = fm.match(X11, X21, D11, D21, idx_init=idx0)
    _assert_share(i_f, i_r, fast, "match idx (idx_init)")
    _assert_share(v_f, v_r, fast, "match valid (idx_init)")


def test_match_batch_axis_and_empty(fast: str) -> None:
    from mslam_fast import matching as fm

    a, b = analytic_pair(40, 30, seed=1), analytic_pair(40, 30, seed=2)
    X11, X21, D11, D21 = (np.stack([x, y]) for x, y in zip(a, b))
    N = 40 * 30
    idx0 = np.random.default_rng(0).integers(0, N, (2, N))
    i_f, v_f = fm.match(X11, X21, D11, D21, idx_init=idx0)
    assert i_f.shape == v_f.shape == (2, N)
    for k, pair in enumerate((a, b)):
        i1, v1 = fm.match(*pair, idx_init=idx0[k])
        np.testing.assert_array_equal(i_f[k], i1)
        np.testing.assert_array_equal(v_f[k], v1)
    i_r, v_r = ref.match(X11, X21, D11, D21, idx_init=idx0)
    _assert_share(i_f.ravel(), i_r.ravel(), fast, "batched idx")
    _assert_share(v_f.ravel(), v_r.ravel(), fast, "batched valid")
    i0, v0 = fm.match(X11[:0], X21[:0], D11[:0], D21[:0])
    assert i0.shape == v0.shape == (0, N) and i0.dtype == np.int64 and v0.dtype == np.bool_


def test_match_zero_and_nonfinite_points(fast: str) -> None:
    from mslam_fast import matching as fm

    X11, X21, D11, D21 = analytic_pair(32, 24)
    X11, X21 = X11.copy(), X21.copy()
    X11[:, 10:13] = 0.0
    X11[5, 5] = np.nan
    X21[3, 4:7] = [[0.0, 0.0, 0.0], [np.inf, 1.0, 1.0], [np.nan, 0.0, 1.0]]
    for cfg in (NO_REFINE, ref.MatchingConfig()):
        i_r, v_r = ref.match(X11, X21, D11, D21, cfg=cfg)
        i_f, v_f = fm.match(X11, X21, D11, D21, cfg=cfg)
        assert np.all((i_f >= 0) & (i_f < 32 * 24))
        assert not v_f[3 * 32 + 4 : 3 * 32 + 7].any()
        _assert_share(i_f, i_r, fast, "idx with bad points")
        _assert_share(v_f, v_r, fast, "valid with bad points")


def test_match_rejects_nonfinite_descriptors(fast: str) -> None:
    """Descriptors are checked by max and min (NaN propagates, ±inf shows), not by a sum
    that could overflow: huge finite values pass, any NaN or inf is named."""
    from mslam_fast import _matching_host as host
    from mslam_fast import matching as fm

    assert host.all_finite(np.full((4, 24), 3e38, np.float32))  # its float32 sum overflows
    assert host.all_finite(np.zeros((0, 24), np.float32))
    X11, X21, D11, D21 = analytic_pair(32, 24)
    for bad in (np.nan, np.inf, -np.inf):
        D = D21.copy()
        D[7, 3, 5] = bad
        assert not host.all_finite(D)
        with pytest.raises(ValueError, match="D21: contains non-finite"):
            fm.match(X11, X21, D11, D)


@pytest.mark.parametrize("stride", [2, 4])
def test_match_on_a_pixel_grid_equals_matching_everything(fast: str, stride: int) -> None:
    """Zeroing the points outside a grid matches the grid only: on the grid both kernel sets
    give what they give when every pixel is matched, off it the clamped start, never valid."""
    from mslam_fast import matching as fm

    X11, X21, D11, D21 = PAIRS["prior-far" if HAVE_PRIOR else "analytic"]
    H, W = X11.shape[:2]
    grid = np.zeros((H, W), bool)
    grid[stride // 2 :: stride, stride // 2 :: stride] = True
    X21_grid = np.where(grid[..., None], X21, 0.0)
    on, off = grid.reshape(-1), ~grid.reshape(-1)
    start = np.clip(np.arange(H * W) % W, 1, W - 2) + W * np.clip(np.arange(H * W) // W, 1, H - 2)
    for mod in (ref, fm):
        i_all, v_all = mod.match(X11, X21, D11, D21)
        i_grid, v_grid = mod.match(X11, X21_grid, D11, D21)
        np.testing.assert_array_equal(i_grid[on], i_all[on])
        np.testing.assert_array_equal(v_grid[on], v_all[on])
        np.testing.assert_array_equal(i_grid[off], start[off])
        assert not v_grid[off].any()


def test_fast_rejects_bad_inputs_like_reference(fast: str) -> None:
    from mslam_fast import matching as fm

    X11, X21, D11, D21 = analytic_pair(16, 12)
    bad_D = D21.copy()
    bad_D[0, 0, 0] = np.inf
    cases = [
        ((X11, X21[:-1], D11, D21), {}, "X21"),
        ((X11, X21, D11[:-1], D21), {}, "D11"),
        ((X11, X21, D11, bad_D), {}, "D21"),
        ((X11, X21, D11, D21), {"idx_init": np.full(16 * 12, -1)}, "idx_init"),
        ((X11, X21, D11, D21), {"idx_init": np.zeros(16 * 12)}, "idx_init"),
    ]
    for args, kw, name in cases:
        for mod in (ref, fm):
            with pytest.raises(ValueError, match=name):
                mod.match(*args, **kw)
    with pytest.raises(ValueError, match="p1"):
        fm.refine_matches(D11, D21.reshape(-1, 24), np.full((16 * 12, 2), 99))


def test_match_with_one_pixel_per_thread(fast: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The LM specialised to one pixel per thread (what CUDA runs) agrees with the reference
    here on the CPU too, so the GPU's variant of the kernel is tested without a GPU."""
    from mslam_fast import matching as fm

    monkeypatch.setattr(fm, "_lanes", lambda: 1)
    X11, X21, D11, D21 = PAIRS["analytic"]
    for cfg in (NO_REFINE, ref.MatchingConfig()):
        i_r, v_r = ref.match(X11, X21, D11, D21, cfg=cfg)
        i_f, v_f = fm.match(X11, X21, D11, D21, cfg=cfg)
        _assert_share(i_f, i_r, fast, f"idx, one pixel per thread, radius {cfg.radius}")
        _assert_share(v_f, v_r, fast, f"valid, one pixel per thread, radius {cfg.radius}")
    H, W = X11.shape[:2]
    n = np.arange(H * W)
    p0 = np.stack([n % W, n // W], -1) + np.random.default_rng(1).uniform(-3, 3, (H * W, 2))
    RG = ref.ray_image_and_gradients(X11)
    p_r, c_r = ref.iter_proj(RG, X21.reshape(-1, 3), p0)
    p_f, c_f = fm.iter_proj(RG, X21.reshape(-1, 3), p0)
    _assert_share(np.floor(p_f), np.floor(p_r), fast, "iter_proj, one pixel per thread")
    _assert_share(c_f, c_r, fast, "iter_proj convergence, one pixel per thread")


@pytest.mark.gpu
@pytest.mark.parametrize("fp", ["f64", "f32"])
def test_match_parity_on_cuda(fp: str) -> None:
    """``match`` on Taichi's CUDA backend against the reference (runs only where a GPU is)."""
    import shutil

    import mslam_fast
    from mslam_fast import matching as fm

    if shutil.which("nvidia-smi") is None:
        pytest.skip("no GPU here")
    try:
        mslam_fast.init("cuda", fp)
        for name, (X11, X21, D11, D21) in PAIRS.items():
            for cfg in (NO_REFINE, ref.MatchingConfig()):
                i_r, v_r = ref.match(X11, X21, D11, D21, cfg=cfg)
                i_f, v_f = fm.match(X11, X21, D11, D21, cfg=cfg)
                _assert_share(i_f, i_r, fp, f"{name} idx on CUDA, radius {cfg.radius}")
                _assert_share(v_f, v_r, fp, f"{name} valid on CUDA, radius {cfg.radius}")
    finally:
        mslam_fast.init("cpu", "f64")
