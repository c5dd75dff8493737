"""docs/getting_started.md runs verbatim: every command of its ``bash`` and ``python`` blocks.

The rule: the blocks run in page order, in one fresh temporary folder that holds a copy of the
repository's ``tutorials/`` (the page's commands run from a clone's root and read nothing else
of it), with the installed package first on ``PATH``. Each command line (a line ending in a
backslash continues) runs as written under ``bash -eo pipefail`` and must exit 0. A line is
skipped when it installs software or serves/builds the site — it contains one of
:data:`SKIPPED` — because the package is already installed here and tests/test_site.py builds
the site.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "getting_started.md"

#: A command line containing one of these is not run (installs, or serves/builds the site).
SKIPPED = ("pip install", "python3 -m venv", "apt-get", "mkdocs serve", "mkdocs build")

#: Longest a single command of the page may take here (the SLAM run: ~10 s on 2 idle cores).
COMMAND_TIMEOUT_S = 600

pytestmark = pytest.mark.slow


def blocks(text: str, lang: str) -> list[str]:
    """The bodies of the fenced ```lang blocks of ``text``, in order."""
    return re.findall(rf"^```{lang}\n(.*?)^```", text, flags=re.M | re.S)


def commands(block: str) -> list[str]:
    """Command lines of a bash block: continuations joined, blank lines and comments dropped."""
    out, cur = [], ""
    for line in block.splitlines():
        cur += line
        if cur.endswith("\\"):
            cur = cur[:-1] + " "
            continue
        if cur.strip() and not cur.lstrip().startswith("#"):
            out.append(cur.strip())
        cur = ""
    return out


def test_block_parsing_follows_the_rule():
    page = "```bash\na --x \\\n  b  # c\n# only a comment\n\npip install -e .\n```\n"
    (block,) = blocks(page, "bash")
    cmds = commands(block)
    assert cmds == ["a --x    b  # c", "pip install -e ."]
    assert [c for c in cmds if not any(s in c for s in SKIPPED)] == ["a --x    b  # c"]


def test_getting_started_runs_verbatim(tmp_path: Path) -> None:
    text = PAGE.read_text()
    shutil.copytree(ROOT / "tutorials", tmp_path / "tutorials")
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "MPLBACKEND": "Agg",
        "OPENBLAS_NUM_THREADS": "1",
    }
    ran = []
    for block in blocks(text, "bash"):
        for cmd in commands(block):
            if any(s in cmd for s in SKIPPED):
                continue
            proc = subprocess.run(
                ["bash", "-eo", "pipefail", "-c", cmd],
                cwd=tmp_path,
                env=env,
                capture_output=True,
                text=True,
                timeout=COMMAND_TIMEOUT_S,
            )
            assert proc.returncode == 0, f"{cmd}\n{proc.stderr[-3000:]}"
            if cmd.startswith("mslam eval"):
                assert json.loads(proc.stdout)["matched"] >= 2, proc.stdout
            ran.append(cmd)
    for block in blocks(text, "python"):
        proc = subprocess.run(
            [sys.executable, "-c", block], cwd=tmp_path, env=env, capture_output=True, text=True
        )
        assert proc.returncode == 0, f"{block}\n{proc.stderr[-3000:]}"
    assert any(c.startswith("mslam run") for c in ran) and any("mslam eval" in c for c in ran)
    assert (tmp_path / "runs" / "demo" / "trajectory.txt").is_file()


def test_notebooks_written_beside_the_tutorials_are_ignored_by_git() -> None:
    """``jupytext --to notebook tutorials/NN_*.py`` (as the page says) leaves no untracked file."""
    git = shutil.which("git")
    if git is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    for path in sorted((ROOT / "tutorials").glob("[0-9][0-9]_*.py")):
        notebook = path.with_suffix(".ipynb").relative_to(ROOT)
        proc = subprocess.run([git, "check-ignore", "-q", str(notebook)], cwd=ROOT)
        assert proc.returncode == 0, f"{notebook} is not ignored by .gitignore"
