"""A folder whose images change size mid-way: one clear error, or a skipped frame with a warning.

A frame of another size, shrunk to the working size, would pass for a view through another lens;
with or without the shrinking (``dataset.long_side`` below or above the images' long side), the
run names the frame and both sizes, writes nothing, and ``--skip-bad-frames`` skips it with a
one-line warning (``mslam.cli``'s warning format).
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from mslam.cli import main

#: Index of the frame of another size.
ODD = 2


def _folder(tmp_path: Path) -> Path:
    """Five textured 64x48 frames with a 40x30 one at :data:`ODD`."""
    import cv2

    rng = np.random.default_rng(0)
    scene = (rng.random((80, 120, 3)) * 255).astype(np.uint8)
    scene = cv2.GaussianBlur(scene, (5, 5), 1.5)
    d = tmp_path / "imgs"
    d.mkdir()
    for i in range(6):
        im = scene[10 : 10 + 48, 4 * i : 4 * i + 64]
        if i == ODD:
            im = cv2.resize(im, (40, 30))
        cv2.imwrite(str(d / f"{i:03d}.png"), im)
    return d


def _argv(src: Path, out: Path, long_side: int) -> list[str]:
    return ["run", str(src), "--prior", "twoview", "--out", str(out), "--kernels", "ref",
            "--quiet", "--set", f"dataset.long_side={long_side}"]  # fmt: skip


@pytest.mark.parametrize("long_side", [32, 160])
def test_a_frame_of_another_size_is_exit_2_without_outputs(tmp_path, capsys, long_side):
    out = tmp_path / "out"
    rc = main(_argv(_folder(tmp_path), out, long_side))
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert f"cannot read frame {ODD}" in err
    assert "40x30" in err or "(30, 40" in err
    assert not out.exists()


def test_a_frame_of_another_size_is_skipped_with_a_one_line_warning(tmp_path, capsys, monkeypatch):
    def show(message, category, filename, lineno, file=None, line=None):
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))

    monkeypatch.setattr(warnings, "showwarning", show)
    before = warnings.formatwarning
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        rc = main([*_argv(_folder(tmp_path), out, 32), "--skip-bad-frames"])
    err = capsys.readouterr().err
    assert rc == 0
    lines = [ln for ln in err.splitlines() if f"skipping frame {ODD}" in ln]
    assert len(lines) == 1 and lines[0].startswith("mslam run: warning: ")
    assert "40x30" in lines[0] and "RuntimeWarning" not in err
    assert warnings.formatwarning is before  # the CLI's format does not outlive the command
    s = json.loads((out / "summary.json").read_text())
    assert s["skipped_frames"] == 1 and [k["frame"] for k in s["skipped"]] == [ODD]
    assert any(f"frame {ODD}" in w and "skipped" in w for w in s["warnings"])
    assert not s["plausible"]  # a frame without a pose is said, not hidden
