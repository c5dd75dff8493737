"""``mslam conformance export DIR`` and ``mslam conformance check DIR --impl MODULE``.

``export`` writes the golden set (``mslam.conformance.export``) into a new or empty folder, all
or nothing. ``check`` runs an implementation (a package with the reference's layout, or an
adapter file ``*.py`` with a ``KERNELS`` dict) on it and prints one row per kernel; exit
status 0 when every provided kernel passes, 1 when any fails, 2 on bad input
(docs/conformance.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["register"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``conformance`` sub-command with its ``export`` and ``check`` actions."""
    p = subparsers.add_parser(
        "conformance",
        help="export golden cases of every kernel, or check an implementation against them",
        description="Golden cases of the kernels (Sim(3), matching, tracking, fusion, backend, "
        "bundle adjustment) with mslam_ref's outputs and tolerances, and a checker that runs "
        "any implementation on them (docs/conformance.md).",
    )
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    e = sub.add_parser("export", help="write the golden set (.npz + index.json) into DIR")
    e.add_argument("dir", type=Path, help="output folder (new or empty)")
    e.add_argument("--overwrite", action="store_true", help="replace a non-empty folder")
    e.set_defaults(func=run_export)
    c = sub.add_parser("check", help="run an implementation on the golden set in DIR")
    c.add_argument("dir", type=Path, help="golden-set folder written by 'export'")
    c.add_argument(
        "--impl",
        required=True,
        help="package with mslam_ref's module layout (mslam_fast, mslam_ref) or an adapter "
        "file ADAPTER.py defining KERNELS = {kernel name: callable}",
    )
    c.add_argument(
        "--precision",
        choices=("f64", "f32"),
        default="f64",
        help="which tolerance column to apply (default f64)",
    )
    c.set_defaults(func=run_check)


def run_export(args: argparse.Namespace) -> int:
    """Write the golden set; prints a JSON summary."""
    from mslam.commands import print_json
    from mslam.conformance.export import write_golden_set
    from mslam.outdir import check_target, staged_folder

    out = check_target(args.dir, args.overwrite, flag="DIR")
    with staged_folder(out, args.overwrite) as tmp:
        summary = write_golden_set(tmp)
    print_json({"out": str(out), **summary})
    return 0


def run_check(args: argparse.Namespace) -> int:
    """Check the implementation; prints the table; 0 all pass, 1 any fails."""
    from mslam.conformance.adapter import load_implementation
    from mslam.conformance.check import format_table, load_golden_set, run_check

    golden = load_golden_set(args.dir)  # bad input is reported before the implementation runs
    impl = load_implementation(args.impl)
    rows = run_check(golden, impl, args.precision)
    print(format_table(rows, impl.name, args.precision))
    return 1 if any(r.verdict == "FAIL" for r in rows) else 0
