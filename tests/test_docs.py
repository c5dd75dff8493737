"""docs/paper_map.md stays true: every function, test file and tutorial it names exists, every
tutorial it names for a row calls one of that row's functions, no page cites files outside
the repository, and no text file of the repository tells the history of its making."""

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
        if len(cells) == 5 and cells[0] not in ("paper", "ba.md") and not set(cells[0]) <= {"-"}:
            rows.append(cells)
    return rows


def _resolve(package: str, dotted: str) -> object:
    parts = dotted.split(".") if dotted else []
    for cut in range(len(parts), -1, -1):
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
            pkg, dotted = ("mslam", name[6:]) if name.startswith("mslam.") else (package, name)
            try:
                _resolve(pkg, dotted)
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


def _tutorial(number: str) -> Path:
    (path,) = (ROOT / "tutorials").glob(f"{number}_*.py")
    return path


def test_tutorials_cover_their_rows() -> None:
    """A tutorial named in a row uses (calls or imports) at least one of the row's functions."""
    uncovered = []
    for row in ROWS:
        names = re.findall(r"`([A-Za-z_][\w.]*)`", row[1])
        for number in re.findall(r"\b(\d\d)\b", row[4]):
            text = _tutorial(number).read_text()
            if not any(re.search(rf"\b{re.escape(n.split('.')[-1])}\b", text) for n in names):
                uncovered.append(f"tutorial {number} does not use any of {names} ({row[0]})")
    assert not uncovered, uncovered


def test_every_tutorial_is_on_the_map() -> None:
    text = MAP.read_text()
    missing = [
        p.stem for p in (ROOT / "tutorials").glob("[0-9][0-9]_*.py") if p.stem[:2] not in text
    ]
    assert not missing, f"tutorials the paper map never names: {missing}"


def test_no_citations_outside_the_repository() -> None:
    """Docs, docstrings and tutorials cite the paper or a docs/ page, not design notes elsewhere."""
    bad = []
    pattern = re.compile(r"\bspec §|\bSpec §|shared/spec|cuda_ba\.md")
    for folder in ("docs", "reference", "fast", "app", "tutorials", "benchmarks"):
        for path in (ROOT / folder).rglob("*"):
            if path.suffix in (".py", ".md", ".yaml") and ".venv" not in path.parts:
                for k, line in enumerate(path.read_text().splitlines(), 1):
                    if pattern.search(line):
                        bad.append(f"{path.relative_to(ROOT)}:{k}")
    for name in ("README.md",):
        for k, line in enumerate((ROOT / name).read_text().splitlines(), 1):
            if pattern.search(line):
                bad.append(f"{name}:{k}")
    assert not bad, f"citations of files outside the repository: {bad}"


def test_reliability_page_names_existing_tests() -> None:
    """docs/reliability.md: every test it names exists in the file it names (or the default
    reliability/guards files)."""
    text = (ROOT / "docs" / "reliability.md").read_text()
    defaults = [
        ROOT / "tests" / "app" / "test_reliability_outputs.py",
        ROOT / "tests" / "app" / "test_reliability_inputs.py",
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


#: Text files of the repository that are scanned for history and outside references.
SCANNED_FOLDERS = (
    ".ci",
    "app",
    "benchmarks",
    "docs",
    "fast",
    "reference",
    "tests",
    "tools",
    "tutorials",
)
SCANNED_TOP = ("README.md", "DEV_NOTES.md", "pyproject.toml", "mkdocs.yml")
SCANNED_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".sh", ".js", ".txt", ".cfg", ""}
SKIPPED_PARTS = {".venv", "build", "site", "__pycache__", ".pytest_cache", ".hypothesis"}
#: History of the work: ticket numbers, sessions, rounds and stops (the character classes keep
#: these patterns from matching themselves).
HISTORY = re.compile(
    r"\b(?:issue|ticke[t])\s*#?\d+"
    r"|\bsession(?:s|'s)?\b"
    r"|\bsto[p]\s+\d+"
    r"|\b(?:this|that|last|previous|next|earlier|first|second|third|fourth|fifth)\s+roun[d]\b",
    re.IGNORECASE,
)
#: pytest's fixture scope is a name, not history.
PYTEST_SCOPE = re.compile(r'scope="session"|session-scoped')
#: Paths and documents outside the repository.
OUTSIDE = re.compile(
    r"\.\./share[d]|\bspe[c]\s*§|shared/(?:spe[c]|desig[n])\b|HOUSE_STYL[E]|/wor[k]/"
)


#: The one file allowed to hold the patterns and their examples: this one.
ALLOWED = {Path(__file__).resolve()}


def _scanned_files() -> list[Path]:
    files = [ROOT / name for name in SCANNED_TOP]
    for folder in SCANNED_FOLDERS:
        for path in sorted((ROOT / folder).rglob("*")):
            rel = path.relative_to(ROOT)
            if (
                path.resolve() not in ALLOWED
                and path.is_file()
                and path.suffix in SCANNED_SUFFIXES
                and not SKIPPED_PARTS & set(rel.parts)
            ):
                files.append(path)
    return files


def _hits(pattern: re.Pattern[str]) -> list[str]:
    hits = []
    for path in _scanned_files():
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        for k, line in enumerate(text.splitlines(), 1):
            match = pattern.search(PYTEST_SCOPE.sub("", line))
            if match:
                hits.append(f"{path.relative_to(ROOT)}:{k}: {match.group(0)}")
    return hits


def test_scanner_patterns() -> None:
    """The patterns catch what they are for and leave the words they must not take."""
    for text in (
        "see issue 17",
        "Issue #4",
        "the third session",
        "sessions",
        "stop 3",
        "this round",
    ):
        assert HISTORY.search(text), text
    for text in ("round(x)", "round trip", "upstream's issues #84", "a non-stop loop"):
        assert not HISTORY.search(text), text
    assert not HISTORY.search(PYTEST_SCOPE.sub("", '@pytest.fixture(scope="session")'))
    for text in ("../shared/data", "spec §3", "shared/design/x.md"):
        assert OUTSIDE.search(text), text
    assert len(_scanned_files()) > 150


def test_no_history_in_the_tree() -> None:
    """Code, tests, docs, benchmarks and tutorials state properties and dated measurements:
    no ticket numbers, no sessions, rounds or stops of the work."""
    hits = _hits(HISTORY)
    assert not hits, "history in the tree:\n" + "\n".join(hits)


def test_nothing_points_outside_the_repository() -> None:
    """No path or document outside the checkout: real data comes from ``MSLAM_DATA``."""
    hits = _hits(OUTSIDE)
    assert not hits, "references outside the repository:\n" + "\n".join(hits)
