"""mslam_fast.fusion against mslam_ref.fusion: every filtering mode, two updates in a row."""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import tol

from mslam_ref import fusion as ref


@pytest.mark.parametrize("mode", ref.FILTERING_MODES)
@pytest.mark.parametrize("shape", [(7,), (6, 5), (0,)])
def test_update_parity(fast: str, mode: str, shape: tuple[int, ...]) -> None:
    from mslam_fast import fusion as fst

    rng = np.random.default_rng(0)
    cfg = ref.FusionConfig(mode)
    X = [rng.normal(0, 1, (*shape, 3)) + np.array([0.0, 0.0, 2.0]) for _ in range(3)]
    C = [rng.uniform(1.0, 3.0, shape) for _ in range(3)]
    sr = sf = ref.init_pointmap(X[0], C[0], cfg)
    for k in (1, 2):
        sr = ref.update_pointmap(sr, X[k], C[k], cfg)
        sf = fst.update_pointmap(sf, X[k], C[k], cfg)
        assert sf.X_canon.shape == (*shape, 3) and sf.C.shape == shape
        assert (sf.N, sf.N_updates) == (sr.N, sr.N_updates) and sf.score == sr.score
        np.testing.assert_allclose(sf.X_canon, sr.X_canon, **tol("fusion", fast))
        np.testing.assert_allclose(sf.C, sr.C, **tol("fusion", fast))
    np.testing.assert_allclose(
        ref.average_confidence(sf), ref.average_confidence(sr), **tol("fusion", fast)
    )


def test_bad_input(fast: str) -> None:
    from mslam_fast import fusion as fst

    s = ref.init_pointmap(np.ones((4, 3)), np.ones(4))
    with pytest.raises(ValueError, match="X"):
        fst.update_pointmap(s, np.ones((3, 3)), np.ones(3))
