"""Every tutorial runs as a notebook (jupytext → nbclient) and shows its figures inline.

The script run (tests/test_tutorials.py) checks the asserts; this test checks what a reader of
the notebook or of the documentation site sees: no cell fails, and every tutorial displays at
least ``MIN_FIGURES`` figures (a ``plt.close(fig)`` or a figure saved to a file instead of shown
would hide them). Needs the ``dev`` extra (jupytext, nbclient, ipykernel); CI installs it.
Executed notebooks are cached in ``build/notebooks/`` (keyed by the tutorial and the library
sources), where the documentation build (tools/mkdocs_hooks.py) picks them up.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = sorted((ROOT / "tutorials").glob("[0-9][0-9]_*.py"))
MIN_FIGURES = 3


def _figures(nb) -> int:
    return sum(
        1
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.get("outputs", [])
        if "image/png" in out.get("data", {})
    )


def _hooks():
    """tools/mkdocs_hooks.py: executes a tutorial into the site's notebook cache."""
    spec = importlib.util.spec_from_file_location(
        "mslam_mkdocs_hooks", ROOT / "tools" / "mkdocs_hooks.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("path", TUTORIALS, ids=lambda p: p.stem)
def test_tutorial_notebook(path: Path) -> None:
    """Executed in a temporary folder; the result also feeds the site build (same cache)."""
    import nbformat

    nb = nbformat.read(_hooks().executed_notebook(path), as_version=4)
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors, f"{path.name}: {errors[0].get('ename')}: {errors[0].get('evalue')}"
    n = _figures(nb)
    assert n >= MIN_FIGURES, f"{path.name}: {n} figures shown inline, expected >= {MIN_FIGURES}"


@pytest.mark.parametrize("path", TUTORIALS, ids=lambda p: p.stem)
def test_tutorial_is_a_course_chapter(path: Path) -> None:
    """Each chapter says what the reader will learn, has exercises and a check cell."""
    text = path.read_text()
    assert text.startswith("# ---\n# jupyter:"), f"{path.name}: no jupytext header"
    assert "What you will learn" in text, f"{path.name}: no 'What you will learn'"
    assert "## Exercises" in text, f"{path.name}: no exercises"
    assert "# Check" in text, f"{path.name}: no check cell for the exercises"
    assert "plt.close(" not in text and "savefig(" not in text, f"{path.name}: hides a figure"
