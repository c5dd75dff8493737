"""Shared pytest set-up: hypothesis profiles, the Taichi runtime fixtures, plotting backend.

* ``HYPOTHESIS_PROFILE`` selects ``ci`` (default: 50 examples per property, derandomised) or
  ``dev`` (10 examples, for quick local loops).
* ``fp`` is a session-scoped parameter ("f64", "f32") so pytest groups the tests of one precision
  together and Taichi is re-initialised rarely; ``fast`` (function scope) re-asserts that precision
  before each test, because other tests may have switched it.
* ``fast64`` pins float64 for tests that only make sense at full precision.
* ``MSLAM_FAST_ARCH`` (``cpu`` by default, or ``cuda``) is the Taichi backend of those two
  fixtures: ``MSLAM_FAST_ARCH=cuda pytest tests/parity`` runs the parity suite on a GPU. With
  ``cuda`` and no GPU the fixtures raise (``mslam_fast.init`` never falls back to the CPU).
* ``MSLAM_DATA`` is the data folder (the 7-Scenes clip in ``seq/``, BAL problems in ``ba/``,
  trajectory pairs in ``traj/``) of the ``shared_data`` fixture and of the tutorials the tests
  run; by default the ``shared/data`` folder beside the checkout. Tests that need it skip
  without it.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
# One BLAS thread: small dense factorisations are 5x slower with two threads on 2 busy cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    max_examples=50,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "dev", max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

#: Taichi backend of the ``fast`` and ``fast64`` fixtures.
FAST_ARCH = os.environ.get("MSLAM_FAST_ARCH", "cpu")

#: The data folder (real sequences, BA problems, trajectories): ``$MSLAM_DATA``, by default the
#: ``shared/data`` folder beside the checkout. Exported so the tutorials the tests run see it too.
SHARED_DATA = Path(
    os.environ.setdefault(
        "MSLAM_DATA", str(Path(__file__).resolve().parents[1].parent / "shared" / "data")
    )
)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The data folder (``MSLAM_DATA``); the test is skipped when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"data folder not found at {SHARED_DATA} (set MSLAM_DATA)")
    return SHARED_DATA


@pytest.fixture(scope="session", params=["f64", "f32"])
def fp(request: pytest.FixtureRequest) -> str:
    """Precision of the fast kernels under test."""
    return str(request.param)


@pytest.fixture
def fast(fp: str) -> str:
    """Initialise mslam_fast on ``FAST_ARCH`` at precision ``fp`` (idempotent); return ``fp``."""
    import mslam_fast

    mslam_fast.init(FAST_ARCH, fp)
    return fp


@pytest.fixture
def fast64() -> str:
    """Initialise mslam_fast on ``FAST_ARCH`` in float64."""
    import mslam_fast

    mslam_fast.init(FAST_ARCH, "f64")
    return "f64"
