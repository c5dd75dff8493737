"""Fast (Taichi) refill and factorisation of the reduced camera system against the reference:
the same solution (both call LAPACK on the same storage), band and dense, and None for an
indefinite or non-finite S."""

from __future__ import annotations

import numpy as np
import pytest

import mslam_ref.ba as R
from mslam_ref.ba import reduced, schur, synthetic


def _reduced_system(problem, lam: float = 0.1):
    cams, pts = problem.params()
    st = schur.build_structure(problem.obs_cam, problem.obs_pt, len(cams), len(pts),
                               problem.cam_dof)  # fmt: skip
    r, Jc, Jp = problem.linearize(R, cams, pts)
    blocks = schur.normal_blocks(r, Jc, Jp, np.ones(len(r)), st)
    S, rhs, _ = schur.schur_complement(*blocks, lam, st)
    return st, S, rhs


@pytest.mark.parametrize("kind", ["banded", "dense"])
def test_parity_factor_solve(fast64: str, kind: str) -> None:
    import mslam_fast.ba as F

    if kind == "banded":
        p, _ = synthetic.make_forward_problem(60, 500, model="pinhole", seed=4)
    else:
        p, _ = synthetic.make_bal_problem(n_cams=5, n_points=30, seed=4)
    st, S, rhs = _reduced_system(p)
    sym = reduced.analyse(st)
    assert sym.kind == kind
    want = reduced.factor_solve(sym, S, rhs)
    for _ in range(2):  # the second call refills the storage the first one factored in place
        got = F.reduced.factor_solve(sym, S, rhs)
        np.testing.assert_array_equal(got, want)
    bad = S.copy()
    bad[st.diag_block[2]] *= -1.0
    assert F.reduced.factor_solve(sym, bad, rhs) is None
    bad = S.copy()
    bad[0, 0, 0] = np.nan
    assert F.reduced.factor_solve(sym, bad, rhs) is None
    np.testing.assert_array_equal(F.reduced.factor_solve(sym, S, rhs), want)
