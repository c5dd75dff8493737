"""The ``mslam`` command: ``run``, ``eval``, ``synth`` and ``ba`` (ARCHITECTURE.md, "Command line").

Each sub-command lives in ``mslam.commands.<name>`` and exposes ``register(subparsers)``,
which adds its parser and sets ``func(args) -> int`` as the default handler. Errors that users can
fix (bad paths, corrupt files, inconsistent calibration, a full disk, missing permissions) are
raised as ``ValueError``, ``OSError`` or ``mslam.commands.UserError`` and printed as one line
with exit code 2; Ctrl-C is exit code 130; a closed stdout pipe ends quietly (docs/reliability.md).
A warning (a skipped frame, a library's notice) is one line, ``mslam COMMAND: warning: ...``,
without the source line Python's default format adds.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

# One BLAS thread before NumPy loads: the small dense factorisations here (BA reduced camera
# system, backend) are several times slower with two threads on a busy 2-core machine.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from collections.abc import Sequence

from mslam import __version__

#: Sub-commands in the order ``mslam --help`` lists them.
COMMANDS = ("run", "eval", "eval_dataset", "synth", "ba", "conformance")


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
    previous = warnings.formatwarning
    warnings.formatwarning = lambda message, *_a, **_k: (
        f"mslam {args.command}: warning: {' '.join(str(message).split())}\n"
    )
    try:
        rc = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe (``| head -1``) shows here, not at exit
        return rc
    except BrokenPipeError:
        _silence_stdout()
        return 0
    except (UserError, ValueError, OSError, MemoryError) as exc:
        print(f"mslam {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mslam {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = previous


def _one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line; an ``OSError`` as ``FILE: reason``."""
    if isinstance(exc, MemoryError):
        return "out of memory (use a smaller input size or frame count)"
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def _silence_stdout() -> None:
    """The reader of stdout went away: send the rest to /dev/null so exit prints nothing."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


if __name__ == "__main__":
    sys.exit(main())
