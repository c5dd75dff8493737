"""Fast (Taichi) BA kernels against the NumPy reference: residuals, Jacobians, Hessian blocks,
Schur system, back-substitution, one LM step and a short LM run."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import LM_COST_HISTORY, LM_POINTS, tol

import mslam_ref.ba as R
from mslam_ref.ba import lm, synthetic
from mslam_ref.ba.robust import RobustKernel


@pytest.fixture(params=["pinhole", "bal"])
def problem(request: pytest.FixtureRequest):
    if request.param == "pinhole":
        p, _ = synthetic.make_pinhole_problem(n_cams=5, n_points=60, stereo_fraction=0.4, seed=11,
                                              kernel=RobustKernel("huber", 2.0))  # fmt: skip
    else:
        p, _ = synthetic.make_bal_problem(n_cams=5, n_points=60, seed=12)
    return p


def _close(a, b, fp: str, scale: float = 1.0) -> None:
    t = tol("ba", fp)
    np.testing.assert_allclose(np.asarray(a, np.float64), b, rtol=t["rtol"], atol=t["atol"] * scale)


def test_parity_linear_system_and_step(fast: str, problem) -> None:
    import mslam_fast.ba as F

    p = problem
    cams, pts = p.params()
    rr = p.linearize(R, cams, pts)
    rf = p.linearize(F, cams, pts)
    for a, b in zip(rf, rr):
        _close(a, b, fast, np.abs(b).max())
    _close(p.residuals(F, cams, pts), p.residuals(R, cams, pts), fast, np.abs(rr[0]).max())
    st = R.schur.build_structure(p.obs_cam, p.obs_pt, len(cams), len(pts), p.cam_dof)
    w = np.random.default_rng(0).uniform(0.5, 1.5, len(rr[0]))
    br = R.schur.normal_blocks(*rr, w, st)
    bf = F.schur.normal_blocks(*rr, w, st)
    for a, b in zip(bf, br):
        _close(a, b, fast, np.abs(b).max())
    jr = R.schur.jacobi_scale(*br, st)
    jf = F.schur.jacobi_scale(*br, st)
    for a, b in zip(jf, jr):
        _close(a, b, fast, np.abs(b).max())
    cam_free, point_free = np.arange(len(cams)) % 3 != 0, np.arange(len(pts)) % 5 != 0
    sr = R.schur.scaled_normal_blocks(*rr, w, cam_free, point_free, st)
    sf = F.schur.scaled_normal_blocks(*rr, w, cam_free, point_free, st)
    assert np.all(sr[0][~cam_free] == 0.25 * np.eye(p.cam_dof))  # identity, scaled by D = 1/2
    for a, b in zip(sf, sr):
        _close(a, b, fast, np.abs(b).max())
    lam = 1e-2 * max(np.abs(br[0]).max(), np.abs(br[1]).max())
    sr = R.schur.schur_complement(*br, lam, st)
    sf = F.schur.schur_complement(*br, lam, st)
    for a, b in zip(sf, sr):
        _close(a, b, fast, np.abs(b).max())
    dc = R.schur.solve_reduced(sr[0], sr[1], st)
    dl_r = R.schur.back_substitute(sr[2], br[2], br[4], dc, st)
    dl_f = F.schur.back_substitute(sr[2], br[2], br[4], dc, st)
    _close(dl_f, dl_r, fast, np.abs(dl_r).max())
    step_r = lm.solve_damped(br, lam, st, R)
    step_f = lm.solve_damped(br, lam, st, F)
    for a, b in zip(step_f, step_r):
        _close(a, b, fast, np.abs(b).max())


def test_parity_lm_run(fast64: str, problem) -> None:
    import mslam_fast.ba as F

    cfg = lm.LMConfig(iterations=5)
    ref = lm.optimize(problem, cfg)
    fst = lm.optimize(problem, cfg, F)
    assert fst.iterations == ref.iterations
    t = tol("ba", "f64")
    np.testing.assert_allclose([h["cost"] for h in fst.history], [h["cost"] for h in ref.history],
                               rtol=LM_COST_HISTORY)  # fmt: skip
    np.testing.assert_allclose(
        fst.problem.points, ref.problem.points, rtol=LM_POINTS, atol=t["atol"] * 1e3
    )


def test_empty_problem_returns_empty(fast64: str) -> None:
    import mslam_fast.ba as F

    e = np.zeros((0,), np.int64)
    r = F.cameras.bal_residuals(np.zeros((1, 9)), np.zeros((1, 3)), e, e, np.zeros((0, 2)))
    assert r.shape == (0, 2)


@pytest.mark.parametrize("model", ["bal", "pinhole"])
def test_parity_lm_banded_reduced_system(fast64: str, model: str) -> None:
    """A forward-moving problem (banded reduced system, analysed once): same costs per iteration
    and the same profile stages, with the symbolic decomposition timed once."""
    import mslam_fast.ba as F

    p, _ = synthetic.make_forward_problem(70, 700, model=model, seed=21)
    cfg = lm.LMConfig(iterations=4, jacobi_scaling=model == "bal")
    ref = lm.optimize(p, cfg)
    fst = lm.optimize(p, cfg, F)
    assert fst.iterations == ref.iterations == 4
    np.testing.assert_allclose([h["cost"] for h in fst.history], [h["cost"] for h in ref.history],
                               rtol=LM_COST_HISTORY)  # fmt: skip
    assert list(fst.profile) == list(lm.PROFILE_KEYS)
    assert fst.profile["symbolic_decomposition"] > 0.0
    assert fst.profile["numerical_decomposition"] > 0.0


def test_recycled_outputs_are_never_shared_with_a_holder(fast64: str, problem) -> None:
    """Large outputs are recycled only once released: a result the caller still holds (or a view
    of it) keeps its values through later calls; a released one lends its memory to the next."""
    import mslam_fast.ba as F
    from mslam_fast._recycle import output

    p = problem
    cams, pts = p.params()
    st = R.schur.build_structure(p.obs_cam, p.obs_pt, len(cams), len(pts), p.cam_dof)
    r, Jc, Jp = p.linearize(R, cams, pts)
    w1, w2 = np.ones(len(r)), np.full(len(r), 2.0)
    held = F.schur.normal_blocks(r, Jc, Jp, w1, st)
    want = R.schur.normal_blocks(r, Jc, Jp, w1, st)
    other = F.schur.normal_blocks(r, Jc, Jp, w2, st)
    assert other[2] is not held[2]
    for a, b in zip(held, want):
        _close(a, b, "f64", np.abs(b).max())
    address = other[2].ctypes.data  # the latest W, which the pool keeps
    del held, other
    again = F.schur.normal_blocks(r, Jc, Jp, w2, st)
    assert again[2].ctypes.data == address  # its memory, released and rewritten
    _close(again[2], 2.0 * want[2], "f64", np.abs(want[2]).max())
    a = output("test", (4, 3), np.float64)
    view = a[1:]
    address = a.ctypes.data
    del a
    assert output("test", (4, 3), np.float64).ctypes.data != address  # a view still holds it
    del view
    assert output("test", (4, 3), np.float64).ctypes.data != address  # replaced in the pool
    b = output("test", (4, 3), np.float64)
    address = b.ctypes.data
    del b
    assert output("test", (4, 3), np.float64).ctypes.data == address
