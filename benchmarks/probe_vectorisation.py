"""Probe: which Taichi access patterns LLVM vectorises on this CPU (docs/matching.md, Performance).

The descriptor refinement of matching wants, for one row of 8 candidates stored contiguously per
channel, ``acc[c] += q[k] * E[row + c]`` for the 8 lanes c: one vector load and one FMA per
channel. This script compiles that inner loop three ways, counts packed (``vfmadd...ps``) and
scalar (``vfmadd...ss``) FMAs in the generated assembly, and times each on 196,608 "pixels"
(one refinement level: 7 rows x 8 lanes x 24 channels per pixel):

* ``ndarray, static lanes``: ``E[base + c]`` for ``c`` in ``ti.static(range(8))``. Taichi indexes
  ndarrays with 32-bit arithmetic, so every lane is ``sext(base + c)`` and the SLP vectoriser
  cannot prove the lanes adjacent;
* ``ndarray, runtime lanes``: the lanes as a runtime loop for LLVM's loop vectoriser; every
  (channel, row) stream needs its own no-wrap check, more than LLVM allows;
* ``Vector.field(24), channel-last``: the layout the kernel in use has; loads are packed (field
  cells are addressed by constant struct offsets) but every dot product ends in a horizontal sum.

Usage: ``python benchmarks/probe_vectorisation.py [--no-write]`` (prints a table and records it
in RESULTS.md, section "vectorisation").
"""

import argparse
import os
import re
import sys
import tempfile
from functools import partial
from pathlib import Path

import numpy as np
import taichi as ti

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import best_of, table, write_section

N, F, ROWS, LANES, PLANE, WS = 196_608, 24, 7, 8, 40_000, 160
nd = ti.types.ndarray()


@ti.kernel
def static_lanes(E: nd, Q: nd, base: nd, out: nd):
    for n in range(out.shape[0]):
        acc = ti.Matrix([[0.0] * LANES for _ in ti.static(range(ROWS))])
        for k in range(F):
            q = Q[n, k]
            for j in ti.static(range(ROWS)):
                for c in ti.static(range(LANES)):
                    acc[j, c] += q * E[base[n] + k * PLANE + j * WS + c]
        out[n] = acc.max()


@ti.kernel
def runtime_lanes(E: nd, Q: nd, base: nd, out: nd, lanes: ti.i32):
    for n in range(out.shape[0]):
        m = 0.0
        for c in range(lanes):
            for j in ti.static(range(ROWS)):
                s = 0.0
                for k in ti.static(range(F)):
                    s += Q[n, k] * E[base[n] + k * PLANE + j * WS + c]
                m = ti.max(m, s)
        out[n] = m


def field_channel_last(D):
    @ti.kernel
    def k(Q: nd, base: nd, out: nd):
        for n in range(out.shape[0]):
            q = ti.Vector([Q[n, k] for k in ti.static(range(F))])
            m = 0.0
            for t in range(ROWS * LANES):
                m = ti.max(m, q.dot(D[base[n] + (t // LANES) * WS + t % LANES]))
            out[n] = m

    return k


def count_ops(folder: Path) -> tuple[int, ...]:
    """In the newest assembly file Taichi wrote into ``folder``: packed FMAs, scalar FMAs,
    single-lane inserts (a vector assembled lane by lane) and ``vmovshdup`` (the last step of a
    horizontal sum)."""
    asm = sorted(folder.glob("*asm*.s"))[-1].read_text()
    pats = (r"vfmadd\w*ps", r"vfmadd\w*ss", r"vinsertps", r"vmovshdup")
    return tuple(len(re.findall(p, asm)) for p in pats)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-write", action="store_true", help="print only, keep RESULTS.md")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    E = rng.random(PLANE * F + 2 * WS * ROWS, dtype=np.float32)
    Q = rng.random((N, F), dtype=np.float32)
    base = np.sort(rng.integers(0, PLANE - WS * ROWS, N)).astype(np.int32)
    out = np.zeros(N, np.float32)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cwd = os.getcwd()
        os.chdir(tmp)  # Taichi writes the assembly files into the working directory
        try:
            ti.init(arch=ti.cpu, default_fp=ti.f32, print_kernel_asm=True, offline_cache=False)
            D = ti.Vector.field(F, ti.f32, shape=PLANE)
            D.from_numpy(rng.random((PLANE, F), dtype=np.float32))
            cases = [
                ("ndarray, static lanes", static_lanes, (E, Q, base, out)),
                ("ndarray, runtime lanes", runtime_lanes, (E, Q, base, out, LANES)),
                ("Vector.field(24), channel-last", field_channel_last(D), (Q, base, out)),
            ]
            for name, fn, fn_args in cases:
                ms = 1e3 * best_of(partial(fn, *fn_args))
                rows.append([name, *count_ops(Path(tmp)), f"{ms:.1f}"])
        finally:
            os.chdir(cwd)
    header = ["inner loop", "packed FMAs", "scalar FMAs", "lane inserts", "horizontal sums"]
    body = table([*header, "ms per level (196,608 pixels)"], rows)
    body += (
        "\n\nInstruction counts are from the assembly Taichi 1.7.4 (LLVM 15) generates for each "
        "kernel; a vector assembled lane by lane (`vinsertps`) is a gather in disguise. Only the "
        "field layout gets packed loads, and it pays a horizontal sum per dot product. "
        "See docs/matching.md, 'Performance'."
    )
    print(body)
    if not args.no_write:
        write_section("vectorisation", "Taichi vectorisation probe (matching refinement)", body)


if __name__ == "__main__":
    main()
