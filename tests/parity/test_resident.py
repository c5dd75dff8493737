"""mslam_fast.resident against the NumPy entries of mslam_fast: the same results bit for bit,
under both storages (the CPU's host arrays, and CUDA's ``ti.ndarray`` path taken on the CPU),
and a keyframe's arrays uploaded once per keyframe, not per frame (upload counters)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import pytest

from mslam_ref import fusion as ref_fusion
from mslam_ref.matching import MatchingConfig

H, W, F = 24, 32, 24
FRAMES = 4
STORAGES = ("numpy", "ndarray")


@contextlib.contextmanager
def _storage(name: str) -> Iterator[None]:
    from mslam_fast import resident

    if name == "numpy" and resident.storage() != "numpy":
        pytest.skip("host-array storage exists only on the CPU backend")
    with resident.ndarrays_on_cpu() if name == "ndarray" else contextlib.nullcontext():
        assert resident.storage() == name
        yield


def _surface(shift: float = 0.0) -> np.ndarray:
    """(H, W, 3) points of a smooth surface in front of the camera, moved by ``shift`` in x."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    z = 2.0 + 0.2 * np.sin(u / 5.0) * np.cos(v / 7.0)
    rays = np.stack([(u - W / 2) / W, (v - H / 2) / H, np.ones_like(u)], axis=-1)
    return rays * z[..., None] + np.array([shift, 0.0, 0.0])


def _descriptors(rng: np.random.Generator, lead: tuple[int, ...] = ()) -> np.ndarray:
    D = rng.normal(size=(*lead, H, W, F)).astype(np.float32)
    return D / np.linalg.norm(D, axis=-1, keepdims=True)


def _view(rng: np.random.Generator, lead: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """A keyframe: its surface (…, H, W, 3) and unit float32 descriptors."""
    return np.broadcast_to(_surface(), (*lead, H, W, 3)).copy(), _descriptors(rng, lead)


def _frames(rng: np.random.Generator, X_kf: np.ndarray, lead: tuple[int, ...] = ()):
    """Per frame: X11 (the frame's surface), X21 (the keyframe's points in the frame's camera,
    with noise), D11 (the frame's descriptors)."""
    for k in range(FRAMES):
        X11 = np.broadcast_to(_surface(0.002 * k), X_kf.shape).copy()
        yield X11, X_kf + rng.normal(0.0, 0.001, X_kf.shape), _descriptors(rng, lead)


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("lead", [(), (2,)])
def test_matcher_equals_match_and_uploads_the_keyframe_once(
    fast: str, storage: str, lead: tuple[int, ...]
) -> None:
    from mslam_fast import matching, resident

    rng = np.random.default_rng(1)
    X_kf, D21 = _view(rng, lead)
    D21.setflags(write=False)  # a prior's cached keyframe descriptors
    matcher = resident.ResidentMatcher()
    resident.reset_uploads()
    idx_np = idx_res = None
    with _storage(storage):
        for X11, X21, D11 in _frames(rng, X_kf, lead):
            idx_a, valid_a = matching.match(X11, X21, D11, D21, idx_np)
            idx_b, valid_b = matcher.match(X11, X21, D11, D21, idx_res)
            assert idx_b.dtype == idx_a.dtype and valid_b.dtype == valid_a.dtype == np.bool_
            np.testing.assert_array_equal(idx_b, idx_a)
            np.testing.assert_array_equal(valid_b, valid_a)
            assert valid_a.mean() > 0.5  # the matches are real, not all rejected
            idx_np, idx_res = idx_a, idx_b
    n = resident.uploads()
    assert matcher.D21_uploads == n["matching.D21"] == 1
    assert n["matching.X11"] == n["matching.X21"] == n["matching.D11"] == FRAMES
    assert "matching.idx_init" not in n  # the previous idx stays on the device


def test_matcher_uploads_a_new_or_writable_keyframe(fast: str) -> None:
    from mslam_fast import resident

    rng = np.random.default_rng(2)
    X_kf, D21 = _view(rng)
    writable = D21.copy()
    D21.setflags(write=False)
    matcher = resident.ResidentMatcher()
    for X11, X21, D11 in _frames(rng, X_kf):
        matcher.match(X11, X21, D11, D21)
    assert matcher.D21_uploads == 1
    other = D21.copy()
    other.setflags(write=False)
    for X11, X21, D11 in _frames(rng, X_kf):
        matcher.match(X11, X21, D11, other)
    assert matcher.D21_uploads == 2  # a new keyframe: once more
    for X11, X21, D11 in _frames(rng, X_kf):
        matcher.match(X11, X21, D11, writable)
    assert matcher.D21_uploads == 2 + FRAMES  # may change in place: every call


def test_matcher_reuploads_after_a_new_taichi_runtime(fast: str) -> None:
    import mslam_fast
    from mslam_fast import resident

    rng = np.random.default_rng(3)
    X_kf, D21 = _view(rng)
    D21.setflags(write=False)
    matcher = resident.ResidentMatcher()
    (X11, X21, D11), *_ = _frames(rng, X_kf)
    matcher.match(X11, X21, D11, D21)
    other = "f32" if fast == "f64" else "f64"
    mslam_fast.init(mslam_fast.current().arch, other)  # frees every ti.ndarray
    try:
        matcher.match(X11, X21, D11, D21)
    finally:
        mslam_fast.init(mslam_fast.current().arch, fast)
    assert matcher.D21_uploads == 2


def test_matcher_checks_like_match(fast: str) -> None:
    from mslam_fast import resident

    rng = np.random.default_rng(4)
    X_kf, D21 = _view(rng)
    bad = D21.copy()
    bad[0, 0, 0] = np.nan
    bad.setflags(write=False)
    (X11, X21, D11), *_ = _frames(rng, X_kf)
    with pytest.raises(ValueError, match="D21"):
        resident.ResidentMatcher().match(X11, X21, D11, bad)
    with pytest.raises(ValueError, match="X21"):
        resident.ResidentMatcher().match(X11, X21[:-1], D11, D21)
    cfg = MatchingConfig(radius=0)  # no refinement: D21 is not read
    idx, valid = resident.ResidentMatcher().match(X11, X21, D11, D21, None, cfg)
    assert idx.shape == valid.shape == (H * W,)


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("mode", ref_fusion.FILTERING_MODES)
def test_fusion_equals_update_pointmap_and_uploads_the_state_once(
    fast: str, storage: str, mode: str
) -> None:
    from mslam_fast import fusion, resident

    rng = np.random.default_rng(5)
    cfg = ref_fusion.FusionConfig(mode)
    X0 = rng.normal(0.0, 1.0, (H * W, 3)) + np.array([0.0, 0.0, 2.0])
    sa = sb = ref_fusion.init_pointmap(X0, rng.uniform(1.0, 3.0, H * W), cfg)
    fuser = resident.ResidentFusion()
    with _storage(storage):
        for _ in range(FRAMES):
            X = X0 + rng.normal(0.0, 0.01, X0.shape)
            C = rng.uniform(1.0, 3.0, H * W)
            sa = fusion.update_pointmap(sa, X, C, cfg)
            sb = fuser.update_pointmap(sb, X, C, cfg)
            np.testing.assert_array_equal(sb.X_canon, sa.X_canon)
            np.testing.assert_array_equal(sb.C, sa.C)
            assert (sb.N, sb.N_updates, sb.score) == (sa.N, sa.N_updates, sa.score)
        kernel_mode = mode in ("weighted_pointmap", "weighted_spherical", "indep_conf")
        assert fuser.state_uploads == int(kernel_mode)
        replaced = ref_fusion.PointmapState(
            sb.X_canon.copy(), sb.C.copy(), sb.N, sb.N_updates, sb.score
        )
        fuser.update_pointmap(replaced, X0, np.ones(H * W), cfg)
        assert fuser.state_uploads == 2 * int(kernel_mode)  # someone else's state: uploaded


def test_solve_uploads_once_per_solve(fast: str) -> None:
    from mslam_fast import resident, tracking
    from mslam_ref import sim3

    rng = np.random.default_rng(6)
    X_k = rng.normal(0.0, 1.0, (H * W, 3)) + np.array([0.0, 0.0, 3.0])
    T = np.concatenate([[0.05, -0.02, 0.03], [0.0, 0.0, 0.0, 1.0], [1.0]])
    X_f = sim3.act(sim3.inv(T), X_k)
    resident.reset_uploads()
    _, info = tracking.solve(X_f, X_k, np.ones(H * W), np.ones(H * W, bool), sim3.identity())
    assert info.iterations > 1  # several linearisations ...
    assert all(resident.uploads()[f"tracking.{a}"] == 1 for a in ("X_f", "X_k", "Q", "valid"))
