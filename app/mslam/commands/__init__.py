"""Sub-commands of the ``mslam`` program, one module each (see ``mslam.cli``)."""

from __future__ import annotations

import json
from typing import Any

from mslam.atomic import write_atomic
from mslam.errors import UserError

__all__ = ["UserError", "print_json", "write_atomic"]


def print_json(obj: dict[str, Any]) -> None:
    """Print a JSON object the way every sub-command reports results."""
    print(json.dumps(obj, indent=2, sort_keys=False, allow_nan=False))
