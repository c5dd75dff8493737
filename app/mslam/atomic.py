"""Atomic output: every file the application writes appears whole or not at all.

One policy for every writer (the formats, a run's outputs, the commands):

* a file is written as ``.NAME.mslam-tmp-PID`` beside its target, with the usual permissions
  (the process umask), then renamed onto the target (:func:`write_atomic`); on any error the
  temporary file is removed and the error propagates;
* a temporary file or folder of a killed process (its PID is gone) is removed by the next
  write to the same target (:func:`remove_stale`).

Whole output *sets* (a run's folder) are staged the same way by
``mslam.outdir.staged_folder``. This module is the bottom of the application: it
imports nothing from ``mslam``.

Public names, in reading order:
    TMP_TAG, temporary_name, write_atomic, remove_stale
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

__all__ = ["TMP_TAG", "remove_stale", "temporary_name", "write_atomic"]

#: Marks the temporary files and folders of a write in progress: ``.NAME`` + TMP_TAG + PID.
TMP_TAG = ".mslam-tmp-"


def temporary_name(path: Path, suffix: str = "") -> Path:
    """``.NAME.mslam-tmp-PID[suffix]`` beside ``path``."""
    return path.with_name(f".{path.name}{TMP_TAG}{suffix}{os.getpid()}")


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (module docstring).

    Args:
        path: the target file; its folder is created when missing.
        data: bytes (written as is) or text.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        _write(tmp, data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def remove_stale(parent: Path, name: str) -> None:
    """Remove the temporary files and folders of writes to ``parent / name`` whose process is
    gone (a killed run); those of live processes are left alone."""
    for p in parent.glob(f".{name}{TMP_TAG}*"):
        pid = p.name.rsplit("-", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)


def _write(path: Path, data: bytes | str) -> None:
    with open(path, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask
