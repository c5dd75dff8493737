"""tools/device_data.py: a packed RGB-D folder unpacks to the same depth pixels and files."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "device_data.py"


def _load():
    spec = importlib.util.spec_from_file_location("device_data", TOOL)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _clip(folder: Path, n: int = 3) -> None:
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        depth = rng.integers(0, 65535, size=(12, 16), dtype=np.uint16)
        assert cv2.imwrite(str(folder / f"frame-{i:06d}.depth.png"), depth)
        (folder / f"frame-{i:06d}.pose.txt").write_text(f"{i}\n")


def test_pack_then_unpack_restores_every_depth_pixel(tmp_path: Path) -> None:
    dd = _load()
    src, dst = tmp_path / "src", tmp_path / "packed"
    _clip(src)
    assert dd.pack(src, dst) == 3
    assert not list(dst.glob("*.depth.png"))
    assert (dst / "frame-000001.pose.txt").read_text() == "1\n"
    assert dd.unpack(dst, verify=src) == 3
    for p in src.glob("*.depth.png"):
        a, b = dd._read_depth(p), dd._read_depth(dst / p.name)
        assert a.dtype == np.uint16 and np.array_equal(a, b)


def test_unpack_refuses_a_name_list_that_does_not_match(tmp_path: Path) -> None:
    dd = _load()
    src, dst = tmp_path / "src", tmp_path / "packed"
    _clip(src)
    dd.pack(src, dst)
    (dst / "depth_names.txt").write_text("frame-000000.depth.png\n")
    with pytest.raises(dd.DataError, match="1 names for 3 depth images"):
        dd.unpack(dst)


def test_pack_without_depth_is_one_line_and_exit_2(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    out = subprocess.run(
        [sys.executable, str(TOOL), "pack", str(tmp_path / "empty"), str(tmp_path / "o")],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"device_data: no *.depth.png in {tmp_path / 'empty'}"
    ]
