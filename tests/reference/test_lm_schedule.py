"""The LM damping schedule (docs/ba.md §5, g2o's ``OptimizationAlgorithmLevenberg``) is pinned.

``lam0 = tau * max diag(H)`` over the free vertices; an accepted trial with gain ratio rho
multiplies lam by ``clamp(1 - (2 rho - 1)^3, 1/3, 2/3)`` and resets nu to 2; a rejected trial
multiplies lam by nu and doubles nu. The history records lam after each iteration, its trials
and the gain ratio of its last trial, so the whole sequence can be replayed.
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import F64_IDENTITY

import mslam_ref.ba as ref_ba
from mslam_ref.ba import lm, schur, synthetic


def _max_diag(problem) -> float:
    cams, pts = problem.params()
    st = schur.build_structure(
        problem.obs_cam, problem.obs_pt, len(cams), len(pts), problem.cam_dof
    )
    r, Jc, Jp = problem.linearize(ref_ba, cams, pts)
    s = problem.information * np.sum(r * r, axis=-1)
    _, w = problem.robust(s)
    U, V, *_ = schur.normal_blocks(r, Jc, Jp, problem.information * w, st)
    diag = np.concatenate(
        [
            np.diagonal(U[problem.cam_free], axis1=1, axis2=2).ravel(),
            np.diagonal(V[problem.point_free], axis1=1, axis2=2).ravel(),
        ]
    )
    return float(diag.max())


def _replay(history, lam0: float) -> list[float]:
    lam, out = lam0, []
    for h in history:
        nu = 2.0
        for _ in range(h["trials"] - 1):  # rejected trials
            lam *= nu
            nu *= 2.0
        if h["accepted"]:
            lam *= min(max(1.0 - (2.0 * h["gain"] - 1.0) ** 3, 1.0 / 3.0), 2.0 / 3.0)
        else:
            lam *= nu
        out.append(lam)
    return out


@pytest.mark.parametrize("tau,perturb", [(1e-5, 0.02), (1e-12, 0.3)])
def test_lambda_schedule_replays(tau: float, perturb: float) -> None:
    problem, _ = synthetic.make_pinhole_problem(n_cams=4, n_points=30, perturb=perturb, seed=1)
    res = lm.optimize(problem, lm.LMConfig(iterations=15, tau=tau))
    lam0 = tau * _max_diag(problem)
    np.testing.assert_allclose(
        [h["lambda"] for h in res.history], _replay(res.history, lam0), rtol=F64_IDENTITY
    )
    for h in res.history:
        assert h["accepted"] == (h["gain"] > 0.0)
        assert 1 <= h["trials"] <= 10


def test_rejections_happen_and_double_nu() -> None:
    """A tiny initial damping on a far start makes Gauss-Newton overshoot: some trials fail."""
    problem, _ = synthetic.make_pinhole_problem(n_cams=4, n_points=30, perturb=0.3, seed=1)
    res = lm.optimize(problem, lm.LMConfig(iterations=15, tau=1e-12))
    assert any(h["trials"] > 1 for h in res.history), [h["trials"] for h in res.history]


def test_accepted_shrink_is_clamped() -> None:
    """The shrink factor stays in [1/3, 2/3] on every accepted single-trial iteration."""
    problem, _ = synthetic.make_pinhole_problem(n_cams=4, n_points=30, seed=2)
    res = lm.optimize(problem, lm.LMConfig(iterations=10))
    prev = None
    for h in res.history:
        if prev is not None and h["trials"] == 1 and h["accepted"]:
            assert 1 / 3 - 1e-12 <= h["lambda"] / prev <= 2 / 3 + 1e-12
        prev = h["lambda"]
