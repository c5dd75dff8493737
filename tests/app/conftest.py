"""Fixtures of the application tests.

* ``rotation_run``: the pure-rotation run through two relocalisations
  (``rotation_scenario.run_rotation``), run once and shared by every rotation test.
"""

from __future__ import annotations

import pytest
from rotation_scenario import RotationRun, run_rotation


@pytest.fixture(scope="session")
def rotation_run() -> RotationRun:
    """The rotation scenario's run and its orientation errors (``rotation_scenario``)."""
    return run_rotation()
