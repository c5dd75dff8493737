"""Every source module stays small: at most ``MAX_MODULE_LINES`` lines.

The rule is DEV_NOTES.md, "Reference functions": small modules (<= ~400 lines), small
functions. It holds for the three packages and for the benchmarks and tools; tests are exempt.
"""

from __future__ import annotations

from pathlib import Path

#: DEV_NOTES.md: "Small modules (<= ~400 lines)"; a module over it is split by topic.
MAX_MODULE_LINES = 400

ROOT = Path(__file__).resolve().parents[1]

#: The folders whose ``*.py`` files the rule covers (a folder that does not exist is skipped).
CHECKED_DIRS = ("app", "fast", "reference", "benchmarks", "tools")


def _line_count(path: Path) -> int:
    """Lines of text in ``path`` (as ``wc -l`` counts them for a file ending in a newline)."""
    return len(path.read_text(encoding="utf-8").splitlines())


def _modules(root: Path) -> list[Path]:
    """Every ``*.py`` under the checked folders of ``root``, hidden folders and caches left out."""
    out = []
    for name in CHECKED_DIRS:
        for path in sorted((root / name).rglob("*.py")):
            parts = path.relative_to(root).parts
            if any(p.startswith(".") or p == "__pycache__" for p in parts):
                continue
            out.append(path)
    return out


def _oversized(root: Path) -> list[str]:
    """``path: N lines`` for each checked module of ``root`` longer than the limit."""
    return [
        f"{p.relative_to(root)}: {n} lines"
        for p in _modules(root)
        if (n := _line_count(p)) > MAX_MODULE_LINES
    ]


def test_every_module_is_at_most_the_limit() -> None:
    modules = _modules(ROOT)
    assert any(p.relative_to(ROOT).parts[0] == "app" for p in modules), "no module found"
    bad = _oversized(ROOT)
    assert not bad, f"modules over {MAX_MODULE_LINES} lines (split them by topic): {bad}"


def test_size_check_names_a_planted_long_module(tmp_path: Path) -> None:
    pkg = tmp_path / "app" / "pkg"
    pkg.mkdir(parents=True)
    (pkg / "long.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    (pkg / "short.py").write_text("x = 1\n" * MAX_MODULE_LINES)
    cache = tmp_path / "app" / "pkg" / "__pycache__"
    cache.mkdir()
    (cache / "long.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    assert _oversized(tmp_path) == [f"app/pkg/long.py: {MAX_MODULE_LINES + 1} lines"]
