"""Pack a 7-Scenes/TUM-style RGB-D folder small enough to travel, and unpack it bit for bit.

A machine reached through a size-limited copy (the lent GPU machine takes 64 MiB in all, wheels
included) cannot take the 150-frame clip as it is (21 MB, 13 MB of it 16-bit depth PNGs). Packed,
the depth images become one xz-compressed ``depth.npy.xz`` (8 MB for the shared clip: LZMA on the
raw 16-bit values beats PNG's deflate); every other file is copied unchanged. Unpacking writes the
depth PNGs back with OpenCV; PNG is lossless, so the decoded depths equal the originals exactly
(``unpack`` checks the frame count, ``--verify SRC`` compares every pixel).

    python tools/device_data.py pack SRC DST      # DST: a folder; SRC is left alone
    python tools/device_data.py unpack DST [--verify SRC]
"""

from __future__ import annotations

import argparse
import lzma
import shutil
import sys
from io import BytesIO
from pathlib import Path

import cv2
import numpy as np

DEPTH_SUFFIX = ".depth.png"
PACKED = "depth.npy.xz"
NAMES = "depth_names.txt"


class DataError(Exception):
    """A folder that cannot be packed or unpacked (one line; exit status 2)."""


def _depth_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.endswith(DEPTH_SUFFIX))


def _read_depth(path: Path) -> np.ndarray:
    """(H, W) uint16 depth image at ``path``."""
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if depth is None:
        raise DataError(f"cannot read {path}")
    return depth


def pack(src: Path, dst: Path) -> int:
    """Copy ``src`` to ``dst`` with its depth PNGs replaced by one packed array; returns the count."""
    files = _depth_files(src)
    if not files:
        raise DataError(f"no *{DEPTH_SUFFIX} in {src}")
    dst.mkdir(parents=True, exist_ok=True)
    for p in sorted(src.iterdir()):
        if p.is_file() and not p.name.endswith(DEPTH_SUFFIX):
            shutil.copy2(p, dst / p.name)
    depth = np.stack([_read_depth(p) for p in files])  # (N, H, W) u16
    buf = BytesIO()
    np.save(buf, depth)
    (dst / PACKED).write_bytes(lzma.compress(buf.getvalue(), preset=9))
    (dst / NAMES).write_text("".join(p.name + "\n" for p in files))
    return len(files)


def unpack(folder: Path, verify: Path | None = None) -> int:
    """Write the depth PNGs of a packed ``folder`` back in place; returns the count."""
    depth = np.load(BytesIO(lzma.decompress((folder / PACKED).read_bytes())))
    names = (folder / NAMES).read_text().split()
    if len(names) != depth.shape[0]:
        raise DataError(f"{len(names)} names for {depth.shape[0]} depth images")
    for name, d in zip(names, depth, strict=True):
        if not cv2.imwrite(str(folder / name), d):
            raise DataError(f"cannot write {folder / name}")
        if verify is not None:
            if not np.array_equal(_read_depth(verify / name), _read_depth(folder / name)):
                raise DataError(f"{name} differs from {verify / name}")
    return len(names)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path)
    u = sub.add_parser("unpack")
    u.add_argument("folder", type=Path)
    u.add_argument("--verify", type=Path, default=None)
    args = ap.parse_args(argv)
    try:
        n = pack(args.src, args.dst) if args.cmd == "pack" else unpack(args.folder, args.verify)
    except (DataError, OSError) as e:
        print(f"device_data: {e}", file=sys.stderr)
        return 2
    print(f"device_data: {args.cmd} {n} depth images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
