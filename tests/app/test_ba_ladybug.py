"""Ladybug-49 (real BAL data): the loader's cost and convergence to Ceres' optimum.

Native Ceres (SPARSE_SCHUR, LM) reaches a cost of 13344.32 in 32 iterations. Here: g2o's LM
schedule with Ceres' Jacobi scaling, at most 50 iterations (cap), stopping on Ceres'
function tolerance 1e-6 (25 iterations, 13345.31, about 4 s on 2 cores).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mslam import bal as io
from mslam_ref.ba import lm

CERES_FINAL = 13344.32
ITERATION_CAP = 50


@pytest.fixture(scope="module")
def ladybug(shared_data: Path):
    return io.read_bal(shared_data / "ba" / "problem-49-7776-pre.txt")


def test_initial_cost_matches_loader_check(ladybug) -> None:
    res = lm.optimize(ladybug, lm.LMConfig(iterations=0))
    assert res.initial_cost == pytest.approx(8.509125e05, rel=1e-6)
    assert (ladybug.cameras.shape, ladybug.points.shape, ladybug.obs.shape) == (
        (49, 9), (7776, 3), (31843, 2))  # fmt: skip


def test_converges_to_ceres_cost(ladybug) -> None:
    cfg = lm.LMConfig(iterations=ITERATION_CAP, jacobi_scaling=True, function_tolerance=1e-6)
    res = lm.optimize(ladybug, cfg)
    assert res.iterations <= ITERATION_CAP
    assert abs(res.final_cost - CERES_FINAL) <= 1e-3 * CERES_FINAL
    costs = [h["cost"] for h in res.history]
    assert np.all(np.diff(costs) <= 0.0)
