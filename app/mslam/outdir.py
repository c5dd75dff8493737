"""One output policy for ``run``, ``synth``, ``ba`` and ``mslam.run`` (docs/reliability.md).

* :func:`check_target` — before any work: the target must not lie below a regular file, must
  not be an existing non-empty folder (or an existing file, for a file target) unless
  ``--overwrite``, and its nearest existing ancestor must be writable.
* :func:`staged_folder` — the whole output set is written into a folder inside a hidden
  temporary folder beside the target (``.NAME.mslam-tmp-PID/NAME``) and moved into place with
  one rename; every temporary file of the writers stays inside that box; on any error or
  Ctrl-C the temporary folder is removed, so the target holds either nothing new or one whole
  set. Temporary folders of killed runs (their PID is gone) are removed by the next run.
* :func:`write_file_atomic` — the same for a single file (``ba --out``), through
  :func:`mslam.atomic.write_atomic`, the one file-writing policy of the application.

Public names, in reading order: check_target, staged_folder, write_file_atomic.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from mslam.atomic import remove_stale, temporary_name, write_atomic
from mslam.errors import UserError

__all__ = ["check_target", "staged_folder", "write_file_atomic"]


def _existing_ancestor(path: Path) -> Path:
    """The nearest existing ancestor of ``path``; a regular file on the way is an error."""
    parent = path.parent if path.parent != path else path
    for anc in [parent, *parent.parents]:
        if anc.exists():
            if not anc.is_dir():
                raise UserError(f"{path}: {anc} is a file, not a folder")
            return anc
    return Path(".")


def check_target(
    out: str | Path, overwrite: bool, kind: str = "folder", flag: str = "--out"
) -> Path:
    """Check an output target before any work starts; returns it as a Path.

    Args:
        out: the target path.
        overwrite: allow replacing an existing non-empty folder (or an existing file).
        kind: ``"folder"`` (run, synth) or ``"file"`` (ba).
        flag: the option named in error messages.

    Raises:
        UserError: naming the path and what was expected.
    """
    out = Path(out)
    anc = _existing_ancestor(out)
    if Path.cwd().resolve().is_relative_to(out.resolve()):
        raise UserError(f"{flag} {out}: is the current folder or contains it; name a new folder")
    if kind == "folder":
        if out.exists() and not out.is_dir():
            raise UserError(f"{flag} {out}: exists and is not a folder")
        if out.is_dir() and any(out.iterdir()) and not overwrite:
            raise UserError(f"{flag} {out}: folder exists and is not empty (use --overwrite)")
    else:
        if out.is_dir():
            raise UserError(f"{flag} {out}: is a folder; expected a file name")
        if out.exists() and not overwrite:
            raise UserError(f"{flag} {out}: file exists (use --overwrite)")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise UserError(f"{flag} {out}: {anc} is not writable")
    return out


def _move_into_place(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` to ``out``; an existing ``out`` (empty, or --overwrite) is moved aside first."""
    if out.is_dir() and any(out.iterdir()):
        old = temporary_name(out, "old-")
        shutil.rmtree(old, ignore_errors=True)
        out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)  # onto an absent target or an empty folder: one rename


@contextlib.contextmanager
def staged_folder(out: str | Path, overwrite: bool) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``out``; on success move it into place.

    The target is checked again at the end (another process may have filled it meanwhile).
    Any exception (including ``KeyboardInterrupt``) removes the temporary folder and
    propagates; an ``OSError`` while writing becomes a one-line :class:`UserError`.
    """
    out = Path(os.path.abspath(check_target(out, overwrite)))
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(out.parent, out.name)
    box = temporary_name(out)
    shutil.rmtree(box, ignore_errors=True)
    box.mkdir()
    stage = box / out.name  # writers that stage on their own (write_tum) stay inside the box
    stage.mkdir()
    try:
        yield stage
        check_target(out, overwrite)
        _move_into_place(stage, out)
    except OSError as exc:
        raise UserError(f"cannot write the outputs to {out}: {exc.strerror or exc}") from None
    finally:
        shutil.rmtree(box, ignore_errors=True)


def write_file_atomic(out: Path, data: bytes | str, overwrite: bool) -> None:
    """Write one output file (``ba --out``) after :func:`check_target`, atomically
    (:func:`mslam.atomic.write_atomic`); a killed writer's temporary file is removed by the
    next write to the same target."""
    out = Path(os.path.abspath(check_target(out, overwrite, kind="file")))
    remove_stale(out.parent, out.name)
    try:
        write_atomic(out, data)
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None
