"""The documentation site builds with ``mkdocs build --strict`` and shows every tutorial's figures.

Marked ``docs``: skipped when the site packages (the ``docs`` extra, part of ``dev``) are absent;
CI installs ``dev`` and runs it. The tutorials are executed through tools/mkdocs_hooks.py's
cache, which tests/test_notebooks.py fills earlier in the same pytest run, so the build itself
mostly renders.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = sorted((ROOT / "tutorials").glob("[0-9][0-9]_*.py"))

pytestmark = pytest.mark.docs


def test_site_builds_strict(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    pytest.importorskip("mkdocs_jupyter")
    pytest.importorskip("mkdocstrings")
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    for path in TUTORIALS:
        page = site / "tutorials" / f"{path.stem}.html"
        assert page.exists(), f"no page for {path.name}"
        html = page.read_text()
        n = len(re.findall(r"<img[^>]+src=\"data:image/png", html))
        assert n >= 3, f"{page.name}: {n} inline figures"
        assert "What you will learn" in html and "Exercises" in html
    for name in (
        "getting_started",
        "paper_map",
        "conventions",
        "architecture",
        "cli",
        "benchmarks",
    ):
        assert (site / f"{name}.html").exists(), name
    api = (site / "api" / "reference.html").read_text()
    assert "mslam_ref.sim3.retract" in api or "retract" in api
