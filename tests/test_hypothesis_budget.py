"""Every hypothesis property (parity ones above all) runs >= 50 examples under the
``ci`` profile; no ``@settings(max_examples=...)`` may lower it."""

from __future__ import annotations

import importlib
import os
from pathlib import Path

import pytest

TESTS = Path(__file__).parent
MODULES = sorted(
    ".".join(p.relative_to(TESTS).with_suffix("").parts)
    for p in TESTS.rglob("test_*.py")
    if p.parent.name in ("parity", "reference")
)


@pytest.mark.skipif(os.environ.get("HYPOTHESIS_PROFILE", "ci") != "ci", reason="ci profile only")
@pytest.mark.parametrize("module", MODULES)
def test_properties_run_at_least_50_examples(module):
    mod = importlib.import_module(module)
    found = {
        name: fn._hypothesis_internal_use_settings.max_examples
        for name, fn in vars(mod).items()
        if name.startswith("test_") and hasattr(fn, "_hypothesis_internal_use_settings")
    }
    low = {k: v for k, v in found.items() if v < 50}
    assert not low, f"{module}: properties below 50 examples: {low}"
