"""Sub-commands of the ``mslam`` program, one module each (see ``mslam.cli``)."""

from __future__ import annotations

import json
from typing import Any

from mslam.atomic import write_atomic

__all__ = ["UserError", "print_json", "write_atomic"]


class UserError(Exception):
    """An error the user can fix; the CLI prints it as one line and exits with status 2."""


def print_json(obj: dict[str, Any]) -> None:
    """Print a JSON object the way every sub-command reports results."""
    print(json.dumps(obj, indent=2, sort_keys=False, allow_nan=False))
