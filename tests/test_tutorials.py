"""Every tutorial ``tutorials/NN_*.py`` runs as a script (its asserts are the checkpoints)."""

from __future__ import annotations

import runpy
import warnings
from pathlib import Path

import pytest

TUTORIALS = sorted((Path(__file__).resolve().parents[1] / "tutorials").glob("[0-9][0-9]_*.py"))


@pytest.mark.parametrize("path", TUTORIALS, ids=lambda p: p.stem)
def test_tutorial_runs(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib

    monkeypatch.setenv("MPLBACKEND", "Agg")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    monkeypatch.chdir(tmp_path)  # anything a tutorial writes lands here, not in the repo
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*non-interactive.*cannot be shown")
            runpy.run_path(str(path), run_name="__main__")
    finally:
        plt.close("all")


def test_tutorials_exist() -> None:
    assert any(p.name == "00_sim3.py" for p in TUTORIALS)
