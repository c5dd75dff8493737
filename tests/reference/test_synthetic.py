"""Synthetic scenes: determinism, exact geometry, camera paths (mslam_ref.synthetic)."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_COPY, F64_IDENTITY, F64_SOLVE

from mslam.datasets.synthetic import make_sequence
from mslam_ref import sim3
from mslam_ref.pointmap import backproject
from mslam_ref.synthetic import (
    PATHS,
    camera_path,
    cast_rays,
    detour_indices,
    jump_indices,
    make_scene,
    render,
)

W, H = 64, 48


@pytest.mark.parametrize("name", PATHS)
def test_sequence_frames_are_valid(name: str) -> None:
    seq = make_sequence(name, n_frames=12, width=W, height=H, seed=3)
    assert len(seq) == 12 and seq.has_depth and seq.K.shape == (3, 3)
    assert seq.T_WC.shape == (12, 8) and seq.name == f"synthetic:{name}"
    for i in (0, 5, -1):
        f = seq[i]
        assert f.rgb.dtype == np.uint8 and f.rgb.shape == (H, W, 3)
        assert f.depth.dtype == np.float64 and f.depth.shape == (H, W)
        assert np.all(np.isfinite(f.depth)) and f.depth.min() > 0.05
        np.testing.assert_array_equal(f.T_WC, seq.T_WC[i % 12])
        assert f.rgb.std() > 10  # textured, not flat
    with pytest.raises(IndexError):
        seq[12]


def test_determinism_by_seed() -> None:
    a = make_sequence("loop", n_frames=6, width=W, height=H, seed=1)[4]
    b = make_sequence("loop", n_frames=6, width=W, height=H, seed=1)[4]
    c = make_sequence("loop", n_frames=6, width=W, height=H, seed=2)[4]
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.T_WC, b.T_WC)
    assert not np.array_equal(a.rgb, c.rgb)


def test_cast_rays_analytic_empty_room() -> None:
    scene = make_scene(0, n_boxes=0, n_spheres=0)
    o = np.array([0.5, -0.25, 1.0])
    dirs = np.array([[0, 0, -1.0], [0, 0, 2.0], [1.0, 0, 0], [0, -1.0, 0], [1.0, 1.0, 0]])
    t, sid = cast_rays(scene, o, dirs)
    np.testing.assert_allclose(t, [1.0, 0.8, 2.5, 2.25, 2.5], rtol=0, atol=F64_COPY)
    assert sid.tolist() == [4, 5, 1, 2, 1]
    with pytest.raises(ValueError, match="origin"):
        cast_rays(scene, np.array([10.0, 0, 1]), dirs)


def test_depth_is_z_along_optical_axis() -> None:
    """Re-casting each pixel's unit-norm ray gives distance = z * |ray|."""
    seq = make_sequence("forward", n_frames=4, width=W, height=H, seed=0)
    f = seq[2]
    M = sim3.to_matrix(f.T_WC)
    X = backproject(f.depth, seq.K).reshape(-1, 3)
    n = np.linalg.norm(X, axis=-1)
    t, _ = cast_rays(seq.scene, M[:3, 3], (X / n[:, None]) @ M[:3, :3].T)
    np.testing.assert_allclose(t, n, rtol=F64_IDENTITY, atol=F64_IDENTITY)


@pytest.mark.parametrize(
    ("name", "i", "j"), [("loop", 0, 2), ("jump", 1, 3), ("detour", 1, 3), ("forward", 0, 2)]
)
def test_two_frames_agree_on_shared_surfaces(name: str, i: int, j: int) -> None:
    """Back-project A under its GT pose, cast B's ray through each point: depths agree to 1e-9.

    Occluders can only be in front of the point, never behind it; most points are unoccluded.
    """
    seq = make_sequence(name, n_frames=30, width=W, height=H, seed=5)
    A, B = seq[i], seq[j]
    MA, MB = sim3.to_matrix(A.T_WC), sim3.to_matrix(B.T_WC)
    P = backproject(A.depth, seq.K).reshape(-1, 3) @ MA[:3, :3].T + MA[:3, 3]
    Xb = (P - MB[:3, 3]) @ MB[:3, :3]  # R_B^T (P - c_B)
    zb = Xb[:, 2]
    front = zb > 0.05
    dirs = (Xb[front] / zb[front, None]) @ MB[:3, :3].T  # unit-z rays of camera B
    t, sid = cast_rays(seq.scene, MB[:3, 3], dirs)
    assert np.all(t <= zb[front] + 1e-9)
    agree = np.abs(t - zb[front]) <= 1e-9
    assert agree.mean() > 0.6
    sid_a = render(seq.scene, A.T_WC, seq.K, W, H)[2].reshape(-1)[front]
    assert np.all(sid[agree] == sid_a[agree])


def test_pixel_centres_reproject_exactly() -> None:
    """B's depth at an integer pixel equals the z of the same world point seen from B."""
    seq = make_sequence("rotation", n_frames=6, width=W, height=H, seed=2)
    A, B = seq[0], seq[1]
    MA, MB = sim3.to_matrix(A.T_WC), sim3.to_matrix(B.T_WC)
    P = backproject(B.depth, seq.K) @ MB[:3, :3].T + MB[:3, 3]  # B's pixel-centre points
    Xa = (P - MA[:3, 3]) @ MA[:3, :3]
    # Pure rotation: the same centre, so every point is visible from A along its ray.
    t, _ = cast_rays(seq.scene, MA[:3, 3], (Xa / Xa[..., 2:]).reshape(-1, 3) @ MA[:3, :3].T)
    np.testing.assert_allclose(t, Xa[..., 2].reshape(-1), rtol=F64_IDENTITY, atol=F64_SOLVE)


def test_paths_shape_the_motion() -> None:
    n = 40
    loop = camera_path("loop", n, seed=0)
    steps = np.linalg.norm(np.diff(loop[:, :3], axis=0), axis=1)
    assert np.linalg.norm(loop[-1, :3] - loop[0, :3]) < 1.5 * steps.max()
    rot = camera_path("rotation", n, seed=0)
    np.testing.assert_allclose(rot[:, :3], rot[:1, :3].repeat(n, 0), atol=0)
    assert np.ptp(rot[:, 3:7], axis=0).max() > 0.1
    fwd = camera_path("forward", n, seed=0)
    assert np.all(np.diff(fwd[:, 0]) > 0)
    detour = camera_path("detour", n, seed=0)
    dsteps = np.linalg.norm(np.diff(detour[:, :3], axis=0), axis=1)
    j1, j2 = detour_indices(n)
    assert set(np.flatnonzero(dsteps > 10 * np.median(dsteps)) + 1) == {j1, j2}
    # After the second jump the camera is back near the first segment.
    d = np.linalg.norm(detour[j2, :3] - detour[:j1, :3], axis=1).min()
    assert d < 0.1
    # Both paths share their seed stream: the same first arc up to the sweep of the heading.
    jump = camera_path("jump", n, seed=0)
    (j,) = jump_indices(n)
    assert j == j1
    np.testing.assert_allclose(jump[:j, :3], detour[:j, :3], atol=F64_IDENTITY)
    jsteps = np.linalg.norm(np.diff(jump[:, :3], axis=0), axis=1)
    assert set(np.flatnonzero(jsteps > 10 * np.median(jsteps)) + 1) == {j}


@pytest.mark.parametrize(("n", "seed"), [(30, 0), (48, 1), (80, 2)])
def test_jump_is_a_kidnap_to_a_mapped_place(n: int, seed: int) -> None:
    """Frame j shares no surface point with the three frames before it (tracking cannot
    follow), frame 0 sees most of its pixels (relocalisation can succeed), and every later frame
    overlaps a frame of the first half by at least 80 % (ground-truth covisibility)."""
    from mslam.priors.synthetic import SyntheticPrior

    seq = make_sequence("jump", n_frames=n, width=W, height=H, seed=seed)
    prior = SyntheticPrior(seq)
    (j,) = jump_indices(n)

    def seen(a: int, b: int) -> float:
        return float(prior.covisible(seq[a], seq[b]).mean())  # share of b's pixels a sees

    assert max(seen(k, j) for k in range(j - 3, j)) == 0.0
    assert seen(0, j) > 0.85
    for i in range(j, n, 3):
        assert max(seen(k, i) for k in range(j)) > 0.8, i
    T = seq.T_WC
    assert 0.02 < np.linalg.norm(T[j, :3] - T[0, :3]) < 0.05  # near, not on, the first pose


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="unknown synthetic path"):
        make_sequence("spiral", n_frames=4, width=W, height=H)
    with pytest.raises(ValueError, match="n_frames"):
        camera_path("loop", 1)
    with pytest.raises(ValueError, match="width"):
        make_sequence("loop", n_frames=4, width=1, height=H)
