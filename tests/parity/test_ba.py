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
