"""Tolerances are named constants of tests/tolerances.py: at most a handful of inline
``atol=``/``rtol=`` number literals remain in the tests, for exact identities (``atol=0``)."""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
INLINE = re.compile(r"\b(?:atol|rtol)\s*=\s*-?\d[\d.]*(?:[eE][-+]?\d+)?")
MAX_INLINE = 30


def _inline_literals() -> list[str]:
    hits = []
    for path in sorted(TESTS.rglob("*.py")):
        if path.name in ("tolerances.py", Path(__file__).name):
            continue
        for k, line in enumerate(path.read_text().splitlines(), 1):
            hits += [f"{path.relative_to(TESTS)}:{k}: {m}" for m in INLINE.findall(line)]
    return hits


def test_pattern_sees_literals_and_not_names() -> None:
    assert INLINE.findall("assert_allclose(a, b, rtol=1e-9, atol=0)") == ["rtol=1e-9", "atol=0"]
    assert not INLINE.findall("assert_allclose(a, b, atol=F64_SOLVE, rtol=t['rtol'])")


def test_few_inline_tolerance_literals() -> None:
    hits = _inline_literals()
    listing = "\n".join(hits)
    assert len(hits) <= MAX_INLINE, f"{len(hits)} inline tolerances (name them):\n{listing}"


def test_inline_literals_that_remain_are_exact() -> None:
    """Outside tests/tolerances.py an inline tolerance is 0: the comparison is exact."""
    inexact = [h for h in _inline_literals() if not re.search(r"=\s*0(?:\.0)?$", h)]
    assert not inexact, "\n".join(inexact)
