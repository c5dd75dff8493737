"""BA reference: the reduced camera system analysed once and refactored per trial (band and dense
storage against a dense solve), the forward-moving problem generator, and the LM profile."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from tolerances import F64_SOLVE, SCHUR_VS_DENSE

import mslam_ref.ba as K
from mslam_ref.ba import lm, reduced, schur, synthetic


def _assert_solves(S, rhs, st, got) -> None:
    """Backward error ``|A x - b| / (|A| |x| + |b|)`` of a Cholesky solve (A badly conditioned
    for BAL cameras, so the solution itself is compared only through its residual)."""
    A = schur.dense_reduced(S, st)
    x = got.ravel()
    err = np.abs(A @ x - rhs.ravel()).max()
    assert err <= F64_SOLVE * (np.abs(A).max() * np.abs(x).max() + np.abs(rhs).max())


def _reduced_system(problem, lam: float = 0.1):
    cams, pts = problem.params()
    st = schur.build_structure(problem.obs_cam, problem.obs_pt, len(cams), len(pts),
                               problem.cam_dof)  # fmt: skip
    r, Jc, Jp = problem.linearize(K, cams, pts)
    blocks = schur.normal_blocks(r, Jc, Jp, np.ones(len(r)), st)
    S, rhs, _ = schur.schur_complement(*blocks, lam, st)
    return st, S, rhs


@pytest.mark.parametrize("model", ["bal", "pinhole"])
def test_banded_solve_equals_dense(model: str) -> None:
    p, _ = synthetic.make_forward_problem(80, 900, model=model, seed=3)
    st, S, rhs = _reduced_system(p)
    sym = reduced.analyse(st)
    assert sym.kind == "banded"
    assert sym.kd <= 12 * p.cam_dof - 1  # runs of at most 12 consecutive views
    _assert_solves(S, rhs, st, reduced.factor_solve(sym, S, rhs))
    if model == "pinhole":  # well conditioned: the solution itself equals the dense one
        want = np.linalg.solve(schur.dense_reduced(S, st), rhs.ravel()).reshape(rhs.shape)
        got = reduced.factor_solve(sym, S, rhs)
        np.testing.assert_allclose(got, want, rtol=SCHUR_VS_DENSE, atol=F64_SOLVE)


def test_wide_pattern_falls_back_to_dense() -> None:
    p, _ = synthetic.make_bal_problem(n_cams=6, n_points=40, views=4, seed=2)
    st, S, rhs = _reduced_system(p)
    sym = reduced.analyse(st)
    assert sym.kind == "dense" and sym.shape == (54, 54)
    _assert_solves(S, rhs, st, reduced.factor_solve(sym, S, rhs))


@pytest.mark.parametrize("kind", ["banded", "dense"])
def test_indefinite_or_nonfinite_gives_none(kind: str) -> None:
    if kind == "banded":
        p, _ = synthetic.make_forward_problem(60, 500, seed=4)
    else:
        p, _ = synthetic.make_bal_problem(n_cams=5, n_points=30, seed=4)
    st, S, rhs = _reduced_system(p)
    sym = reduced.analyse(st)
    assert sym.kind == kind
    bad = S.copy()
    bad[st.diag_block[2]] *= -1.0
    assert reduced.factor_solve(sym, bad, rhs) is None
    bad = S.copy()
    bad[0, 0, 0] = np.nan
    assert reduced.factor_solve(sym, bad, rhs) is None


def test_ordering_packs_a_shuffled_chain() -> None:
    """Cameras numbered in random order: the ordering recovers the chain's narrow band."""
    p, _ = synthetic.make_forward_problem(60, 800, seed=5)
    shuffle = np.random.default_rng(0).permutation(60)
    st = schur.build_structure(shuffle[p.obs_cam], p.obs_pt, 60, 800, 9)
    sym = reduced.analyse(st)
    assert sym.kind == "banded" and sym.kd <= 12 * 9 - 1
    assert sorted(sym.perm.tolist()) == list(range(60))
    np.testing.assert_array_equal(sym.perm[sym.inv_perm], np.arange(60))


def test_forward_problem_runs_of_consecutive_views() -> None:
    p, truth = synthetic.make_forward_problem(50, 500, mean_views=4.0, seed=6)
    for j in range(500):
        cams = np.sort(p.obs_cam[p.obs_pt == j])
        assert 2 <= len(cams) <= 12
        np.testing.assert_array_equal(np.diff(cams), 1)
    cams, pts = truth.params()
    r = truth.residuals(K, cams, pts)
    assert np.sqrt(np.mean(r**2)) < 1.0  # noise 0.5 px at the truth
    with pytest.raises(ValueError, match="model"):
        synthetic.make_forward_problem(5, 10, model="fisheye")


def test_symbolic_once_numeric_per_trial() -> None:
    calls = {"analyse": 0, "factor_solve": 0}

    def analyse(st):
        calls["analyse"] += 1
        return reduced.analyse(st)

    def factor_solve(sym, S, rhs):
        calls["factor_solve"] += 1
        return reduced.factor_solve(sym, S, rhs)

    kernels = SimpleNamespace(cameras=K.cameras, schur=K.schur,
                              reduced=SimpleNamespace(analyse=analyse, factor_solve=factor_solve))  # fmt: skip
    p, _ = synthetic.make_forward_problem(60, 600, seed=7)
    res = lm.optimize(p, lm.LMConfig(iterations=6, jacobi_scaling=True), kernels)
    assert calls["analyse"] == 1
    assert calls["factor_solve"] == sum(h["trials"] for h in res.history)
    assert res.profile["symbolic_decomposition"] > 0.0
    assert res.final_cost < 0.1 * res.initial_cost
    ref = lm.optimize(p, lm.LMConfig(iterations=6, jacobi_scaling=True))
    assert ref.final_cost == res.final_cost
