"""Benchmark: Sim(3) ``act`` and ``exp`` on 1e6 elements, reference (NumPy) vs fast (Taichi CPU).

For each fast precision the table shows the public wrapper (validation + coercion + kernel) and
the kernel alone on prepared arrays (``mslam_fast.sim3._act_k`` / ``_exp_k``), so the share of
host-side work is visible. Best of 5 after a warm-up call (which also pays the kernel compile).

Run: ``python benchmarks/bench_sim3.py [--n 1000000] [--repeat 5] [--no-write]``.
Rewrites the "sim3" section of benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

try:  # an editable install makes this unnecessary
    import mslam_fast
except ImportError:  # pragma: no cover - running from a bare checkout
    root = Path(__file__).resolve().parents[1]
    sys.path[:0] = [str(root / "reference"), str(root / "fast")]

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import best_of, table, write_section

import mslam_fast
import mslam_fast.sim3 as F
from mslam_ref import sim3 as R


def ms(seconds: float) -> str:
    return f"{1e3 * seconds:.1f}"


def _fast_row(
    fp: str,
    T: np.ndarray,
    X: np.ndarray,
    xi: np.ndarray,
    rep: int,
    t_ref_act: float,
    t_ref_exp: float,
) -> list[object]:
    """Wrapper and kernel-only timings of the fast act and exp at precision ``fp``."""
    mslam_fast.init("cpu", fp)
    dt = mslam_fast.current().dtype
    T_, X_, xi_ = (np.ascontiguousarray(a, dtype=dt) for a in (T, X, xi))
    n = T.shape[0]
    out3, out8 = np.empty((n, 3), dt), np.empty((n, 8), dt)
    t_act = best_of(lambda: F.act(T, X), rep)
    t_act_k = best_of(lambda: F._act_k(T_, X_, out3), rep)
    t_exp = best_of(lambda: F.exp(xi), rep)
    t_exp_k = best_of(lambda: F._exp_k(xi_, out8), rep)
    speed = f"{t_ref_act / t_act:.1f}x / {t_ref_exp / t_exp:.1f}x"
    return [f"fast (Taichi CPU {fp})", ms(t_act), ms(t_act_k), ms(t_exp), ms(t_exp_k), speed]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-write", action="store_true", help="print only, leave RESULTS.md")
    args = ap.parse_args()
    n, rep = args.n, args.repeat

    rng = np.random.default_rng(0)
    xi = rng.normal(size=(n, 7)) * 0.5
    T = R.exp(xi)
    X = rng.normal(size=(n, 3)) * 3.0

    t_ref_act = best_of(lambda: R.act(T, X), rep)
    t_ref_exp = best_of(lambda: R.exp(xi), rep)
    rows = [["reference (NumPy f64)", ms(t_ref_act), "-", ms(t_ref_exp), "-", "1.0x / 1.0x"]]
    for fp in ("f64", "f32"):
        rows.append(_fast_row(fp, T, X, xi, rep, t_ref_act, t_ref_exp))

    header = [
        "implementation",
        "act (ms)",
        "act kernel only (ms)",
        "exp (ms)",
        "exp kernel only (ms)",
        "speed-up act / exp",
    ]
    body = (
        f"{n:,} elements, best of {rep} after a warm-up call. `act` maps points by "
        "`s R X + t`; `exp` maps tangents to group elements. *Kernel only* times "
        "`mslam_fast.sim3._act_k` / `_exp_k` on arrays already validated, normalised and cast; "
        "the difference to the wrapper is host-side work (finiteness and scale checks, "
        "quaternion norms, dtype casts for f32 inputs, output allocation).\n\n"
        + table(header, rows)
    )
    print(body)
    if not args.no_write:
        write_section("sim3", f"Sim(3) act and exp, {n:.0e} elements".replace("+0", ""), body)


if __name__ == "__main__":
    main()
