"""docs/paper_map.md stays true: every function, test file and tutorial it names exists."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAP = ROOT / "docs" / "paper_map.md"


def _rows() -> list[list[str]]:
    rows = []
    for line in MAP.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if (
            len(cells) == 5
            and cells[0] not in ("paper / spec", "spec")
            and not set(cells[0]) <= {"-"}
        ):
            rows.append(cells)
    return rows


def _resolve(package: str, dotted: str) -> object:
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join([package, *parts[:cut]]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(f"{package}.{dotted}")


ROWS = _rows()


def test_map_has_rows() -> None:
    assert len(ROWS) > 40


@pytest.mark.parametrize("column,package", [(1, "mslam_ref"), (2, "mslam_fast")])
def test_named_functions_exist(column: int, package: str) -> None:
    missing = []
    for row in ROWS:
        for name in re.findall(r"`([A-Za-z_][\w.]*)`", row[column]):
            try:
                _resolve(package, name)
            except (ModuleNotFoundError, AttributeError):
                missing.append(f"{package}.{name}")
    assert not missing, f"paper_map names objects that do not exist: {missing}"


def test_named_tests_and_tutorials_exist() -> None:
    missing = []
    for row in ROWS:
        for ref in re.findall(r"([a-z]+/test_\w+)", row[3]):
            if not (ROOT / "tests" / f"{ref}.py").exists():
                missing.append(ref)
        for number in re.findall(r"\b(\d\d)\b", row[4]):
            if not list((ROOT / "tutorials").glob(f"{number}_*.py")):
                missing.append(f"tutorial {number}")
    assert not missing, f"paper_map names missing tests/tutorials: {missing}"


def test_reliability_page_names_existing_tests() -> None:
    """docs/reliability.md: every test it names exists in the file it names (or the default
    reliability/guards files)."""
    text = (ROOT / "docs" / "reliability.md").read_text()
    defaults = [
        ROOT / "tests" / "system" / "test_reliability_outputs.py",
        ROOT / "tests" / "system" / "test_reliability_inputs.py",
        ROOT / "tests" / "parity" / "test_guards.py",
    ]
    sources = "".join(p.read_text() for p in defaults)
    missing = []
    for path, name in re.findall(r"`(?:(tests/[\w/]+\.py)::)?(test_\w+)`", text):
        src = (ROOT / path).read_text() if path else sources
        if f"def {name}(" not in src:
            missing.append(f"{path or 'reliability tests'}::{name}")
    for path in re.findall(r"`(tests/[\w/]+\.py)`", text):
        if not (ROOT / path).exists():
            missing.append(path)
    assert not missing, f"docs/reliability.md names missing tests: {missing}"
