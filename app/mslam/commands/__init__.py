"""Sub-commands of the ``mslam`` program, one module each (see ``mslam.cli``)."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


class UserError(Exception):
    """An error the user can fix; the CLI prints it as one line and exits with status 2."""


def print_json(obj: dict[str, Any]) -> None:
    """Print a JSON object the way every sub-command reports results."""
    print(json.dumps(obj, indent=2, sort_keys=False, allow_nan=False))


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename, never leaving a partial file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as fh:
            fh.write(data)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask
