"""The ``mslam`` command: ``run``, ``eval``, ``synth`` and ``ba`` (ARCHITECTURE.md, "Command line").

Each sub-command lives in ``mslam.commands.<name>`` and exposes ``register(subparsers)``,
which adds its parser and sets ``func(args) -> int`` as the default handler. Errors that users can
fix (bad paths, corrupt files, inconsistent calibration) are raised as ``ValueError``,
``FileNotFoundError`` or ``mslam.commands.UserError`` and printed as one line with exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# One BLAS thread before NumPy loads: the small dense factorisations here (BA reduced camera
# system, backend) are several times slower with two threads on a busy 2-core machine.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from collections.abc import Sequence

from mslam import __version__

#: Sub-commands in the order ``mslam --help`` lists them.
COMMANDS = ("run", "eval", "eval_dataset", "synth", "ba")


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every available sub-command registered."""
    parser = argparse.ArgumentParser(
        prog="mslam",
        description="MASt3R-SLAM education and reference implementation (NumPy reference, "
        "Taichi fast kernels) and an LM/Schur bundle adjuster.",
    )
    parser.add_argument("--version", action="version", version=f"mslam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"mslam.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    from mslam.commands import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except (UserError, ValueError, FileNotFoundError) as exc:
        print(f"mslam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mslam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
