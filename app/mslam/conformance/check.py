"""Check an implementation against a golden set: run every case, compare, one row per kernel.

The golden set is read and validated completely before anything runs (a missing folder, a
broken ``index.json`` or a corrupt or inconsistent case file is a ``ValueError``). Each
case calls the implementation with the reference's signature
(``mslam.conformance.kernels.call``) and compares every output with the measure and the
tolerance the index states for the chosen precision. A kernel passes when every case passes;
an exception in the implementation fails the case.

Public names, in reading order:
    Row, load_golden_set, compare, run_check, format_table
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from mslam.conformance.adapter import Implementation
from mslam.conformance.export import FORMAT, VERSION
from mslam.conformance.kernels import KERNELS, call
from mslam.conformance.tolerances import PRECISIONS

__all__ = ["Row", "compare", "format_table", "load_golden_set", "run_check"]


@dataclasses.dataclass
class Row:
    """One kernel's result: cases run, the worst output seen and the verdict.

    Attributes:
        kernel: kernel name. cases: number of cases. worst: ``case/output`` of the worst
        comparison. error: its error as text. tolerance: its tolerance as text.
        badness: error relative to tolerance (<= 1 passes; inf for an exception).
        verdict: ``ok``, ``FAIL`` or ``absent``.
    """

    kernel: str
    cases: int = 0
    worst: str = "-"
    error: str = "-"
    tolerance: str = "-"
    badness: float = -1.0
    verdict: str = "ok"


def load_golden_set(folder: str | Path) -> tuple[dict[str, Any], list[tuple[dict, dict, dict]]]:
    """Read ``index.json`` and every case file of ``folder``.

    Returns:
        (index, [(case entry, inputs, reference outputs)]), arrays without their prefix.

    Raises:
        ValueError: a missing folder or index, an index of another format, an unknown kernel,
            or a case file that is missing, corrupt or disagrees with the index.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such golden-set folder")
    path = folder / "index.json"
    try:
        index = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: missing (run 'mslam conformance export' first)") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} index")
    if index.get("version") != VERSION:
        raise ValueError(f"{path}: version {index.get('version')!r}, this mslam reads {VERSION}")
    cases = []
    for entry in index.get("cases", []):
        _check_entry(path, index, entry)
        cases.append((entry, *_load_case(folder, entry)))
    if not cases:
        raise ValueError(f"{path}: lists no cases")
    return index, cases


#: The tolerance parameters each measure reads.
_NEEDS = {"allclose": ("rtol", "atol"), "scaled": ("rtol", "atol"), "exact": (),
          "share_equal": ("share",), "share_close": ("share", "atol")}  # fmt: skip


def _valid_tolerance(o: dict[str, Any]) -> bool:
    """``o`` has a known measure and, per precision, the numbers that measure reads."""
    measure = o.get("measure")
    need = _NEEDS.get(measure) if isinstance(measure, str) else None
    return need is not None and all(
        isinstance(o.get(fp), dict) and all(isinstance(o[fp].get(k), int | float) for k in need)
        for fp in PRECISIONS
    )


def _check_entry(path: Path, index: dict[str, Any], entry: Any) -> None:
    """A case entry names a known kernel whose outputs have a measure and both tolerances."""
    if not isinstance(entry, dict) or not all(
        isinstance(entry.get(k), str) for k in ("kernel", "name", "file")
    ):
        raise ValueError(f"{path}: a case entry lacks 'kernel', 'name' or 'file'")
    fps = entry.get("precisions", list(PRECISIONS))
    if not isinstance(fps, list) or not set(fps) <= set(PRECISIONS):
        raise ValueError(f"{path}: case {entry['file']}: 'precisions' must list f64 and/or f32")
    kernel = entry["kernel"]
    spec = index.get("kernels", {}).get(kernel) if isinstance(index.get("kernels"), dict) else None
    if kernel not in KERNELS or not isinstance(spec, dict):
        raise ValueError(f"{path}: unknown kernel {kernel!r}")
    outputs = spec.get("outputs", {})
    for name in KERNELS[kernel].outputs:
        o = outputs.get(name) if isinstance(outputs, dict) else None
        if not isinstance(o, dict) or not _valid_tolerance(o):
            raise ValueError(f"{path}: kernel {kernel} output {name}: no valid measure/tolerance")


def _load_case(folder: Path, entry: dict[str, Any]) -> tuple[dict, dict]:
    """Inputs and outputs of one case file, checked against the index's shapes and dtypes."""
    path = folder / str(entry.get("file", ""))
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise ValueError(f"{path}: case file missing") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: corrupt case file ({exc})") from None
    want = entry.get("arrays", {})
    got = {n: {"shape": list(a.shape), "dtype": a.dtype.str} for n, a in arrays.items()}
    if got != want:
        raise ValueError(f"{path}: entries differ from index.json (names, shapes or dtypes)")
    ins = {k[3:]: v for k, v in arrays.items() if k.startswith("in.")}
    outs = {k[4:]: v for k, v in arrays.items() if k.startswith("out.")}
    if set(outs) != set(KERNELS[entry["kernel"]].outputs):
        raise ValueError(f"{path}: outputs {sorted(outs)} do not match kernel {entry['kernel']}")
    return ins, outs


def compare(got: Any, want: np.ndarray, measure: str, tol: dict[str, float]):
    """Compare one output with the reference.

    Returns:
        (badness, error text, tolerance text); badness <= 1 passes.
    """
    g = np.asarray(got)
    if g.shape != want.shape and not (want.ndim == 0 and g.size == 1):
        return np.inf, f"shape {g.shape} != {want.shape}", "-"
    g = g.reshape(want.shape)
    if measure in ("allclose", "scaled"):
        return _close(g.astype(np.float64), want.astype(np.float64), measure, tol)
    if measure == "exact":
        n = int(np.sum(g != want))
        return (np.inf if n else 0.0), f"{n} differ", "equal"
    if measure == "share_equal":
        share = float(np.mean(g == want)) if want.size else 1.0
    else:  # share_close: rows of the last axis within atol
        ok = np.all(np.abs(g.astype(np.float64) - want) <= tol["atol"], axis=-1)
        share = float(np.mean(ok)) if ok.size else 1.0
    req = tol["share"]
    bad = 0.0 if share >= req else 1.0 + (req - share)
    within = f" within {tol['atol']:g}" if "atol" in tol else ""
    return bad, f"share {share:.4f}", f"share{within} >= {req:g}"


def _close(g: np.ndarray, w: np.ndarray, measure: str, tol: dict[str, float]):
    scale = float(np.max(np.abs(w), initial=0.0, where=np.isfinite(w)))
    scale = scale if measure == "scaled" else 1.0
    allowed = tol["atol"] * scale + tol["rtol"] * np.abs(w)
    same = (g == w) | (np.isnan(g) & np.isnan(w))
    err = np.where(same, 0.0, np.abs(g - w))
    err = np.where(np.isnan(err), np.inf, err)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(err == 0, 0.0, err / allowed)
    bad = float(np.max(ratio, initial=0.0))
    s = " max|ref|" if measure == "scaled" else ""
    lost = int(np.sum(~np.isfinite(g) & np.isfinite(w)))  # NaN/inf where the reference is finite
    text = f"{lost} non-finite" if lost else f"{float(np.max(err, initial=0.0)):.2e}"
    return bad, text, f"{tol['atol']:g}{s} + {tol['rtol']:g}|ref|"


def _run_case(fn: Any, entry: dict, ins: dict, outs: dict, tols: dict, fp: str):
    """(badness, where, error, tolerance) of the worst output of one case."""
    kernel = KERNELS[entry["kernel"]]
    try:
        got = call(kernel, fn, dict(ins), entry.get("params", {}))
    except Exception as exc:  # the implementation under test failed: a finding, not a crash
        text = " ".join(f"{type(exc).__name__}: {exc}".split())
        return np.inf, entry["name"], text[:60], "-"
    worst = (-1.0, "", "", "")
    for name, want in outs.items():
        spec = tols[name]
        bad, err, tol = compare(got[name], want, spec["measure"], spec[fp])
        if bad > worst[0]:
            worst = (bad, f"{entry['name']}/{name}", err, tol)
    return worst


def run_check(golden: tuple[dict, list], impl: Implementation, fp: str = "f64") -> list[Row]:
    """Run ``impl`` on every case of ``golden`` (from :func:`load_golden_set`).

    Returns:
        One :class:`Row` per kernel of the index, in reading order.
    """
    index, cases = golden
    rows = {name: Row(name) for name in KERNELS if name in index["kernels"]}
    for entry, ins, outs in cases:
        row = rows[entry["kernel"]]
        if fp not in entry.get("precisions", PRECISIONS):
            continue  # e.g. scales near the Sim(3) cap that float32 cannot represent
        fn = impl.functions.get(row.kernel)
        if fn is None:
            row.verdict = "absent"
            continue
        tols = index["kernels"][row.kernel]["outputs"]
        bad, where, err, tol = _run_case(fn, entry, ins, outs, tols, fp)
        row.cases += 1
        if bad > row.badness:
            row.badness, row.worst, row.error, row.tolerance = bad, where, err, tol
        if bad > 1.0:
            row.verdict = "FAIL"
    return list(rows.values())


def _ratio(r: Row) -> str:
    return "-" if r.badness < 0 or not np.isfinite(r.badness) else f"{r.badness:.1e}"


def format_table(rows: list[Row], impl: str, fp: str) -> str:
    """The report: one line per kernel and a summary line."""
    head = ("kernel", "cases", "worst case/output", "error", "tolerance", "err/tol", "verdict")
    lines = [head] + [
        (r.kernel, str(r.cases), r.worst, r.error, r.tolerance, _ratio(r), r.verdict) for r in rows
    ]
    widths = [max(len(line[c]) for line in lines) for c in range(len(head))]
    out = [f"conformance of {impl} ({fp})"]
    out += ["  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
            for line in lines]  # fmt: skip
    n = {v: sum(r.verdict == v for r in rows) for v in ("ok", "FAIL", "absent")}
    out.append(f"{n['ok']} ok, {n['FAIL']} failed, {n['absent']} absent of {len(rows)} kernels")
    return "\n".join(out)
