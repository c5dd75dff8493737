"""Write the conformance golden set: every case's inputs, the reference's outputs, an index.

Layout of a golden-set folder::

    index.json                   format, conventions, measures, kernels, cases (see below)
    KERNEL/CASE.npz              e.g. sim3.act/edges.npz

Each ``.npz`` is a zip archive whose entries are *stored* (no compression) ``.npy`` files of
format version 1.0, little-endian: ``in.NAME.npy`` for the kernel's array arguments and
``out.NAME.npy`` for the reference's results (``mslam_ref``, float64). Dtypes are ``<f8``,
``<i8`` and ``|b1`` only; a 0-d array holds a scalar result (a cost, a flag). ``index.json``
lists per case the file, the ``params`` (configuration and scalars), the shape and dtype of
every entry, and per kernel its signature and, per output, the measure and the f64 and f32
tolerances (``mslam.conformance.tolerances``).

Public names, in reading order:
    CONVENTIONS, FORMAT, VERSION, reference_outputs, write_golden_set
"""

from __future__ import annotations

import dataclasses
import importlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from mslam.conformance.cases import Case, build_cases
from mslam.conformance.kernels import KERNELS, Kernel, call
from mslam.conformance.tolerances import MEASURES, PRECISIONS, tolerance_for

__all__ = ["CONVENTIONS", "FORMAT", "VERSION", "reference_outputs", "write_golden_set"]

FORMAT = "mslam-conformance"
VERSION = 1

#: The conventions every case follows, stated in ``index.json``.
CONVENTIONS = {
    "sim3_element": "T = [tx, ty, tz, qx, qy, qz, qw, s], shape (..., 8): translation, unit "
    "Hamilton quaternion in x, y, z, w order, scale s > 0 stored directly; matrix "
    "[[s R, t], [0, 1]]; T . X = s R X + t",
    "sim3_tangent": "xi = [tau (3), phi (3), sigma], shape (..., 7): translation part, "
    "rotation vector, log-scale",
    "retraction": "left: retract(T, xi) = Exp(xi) . T; Jacobians are with respect to a left "
    "perturbation Exp(delta) . T",
    "frames": "monogram T_AB maps points in frame B into frame A (X_A = T_AB . X_B); T_CkCf: "
    "current frame f into keyframe k; T_WC: camera into world",
    "pixels": "(u, v) = (column, row); linear pixel index n = u + W v; N = H W",
    "se3_pose": "BA pinhole poses [tx, ty, tz, qx, qy, qz, qw], world to camera",
    "batch": "leading axes (...) are batch axes; an empty batch (0, ...) gives empty outputs",
    "precision": "inputs and reference outputs are float64; integers int64; masks bool",
}


def reference_outputs(kernel: Kernel, case: Case) -> dict[str, np.ndarray]:
    """The reference's (``mslam_ref``) outputs of ``case``, by output name."""
    mod = importlib.import_module(f"mslam_ref.{kernel.module}")
    out = call(kernel, getattr(mod, kernel.function), case.inputs, case.params)
    return {k: _canonical(v) for k, v in out.items()}


def _canonical(a: Any) -> np.ndarray:
    """``a`` as one of the three stored dtypes (float64, int64, bool), C order."""
    a = np.asarray(a)
    if a.dtype == np.bool_:
        return np.asarray(a, order="C")
    if np.issubdtype(a.dtype, np.integer):
        return np.asarray(a, dtype="<i8", order="C")
    return np.asarray(a, dtype="<f8", order="C")


def _kernel_entry(k: Kernel) -> dict[str, Any]:
    outputs = {}
    for name, measure in k.outputs.items():
        m, role = ("allclose", "pose") if measure == "pose" else (measure, "")
        outputs[name] = {"measure": m, **{fp: tolerance_for(k.group, m, fp, role)
                                          for fp in PRECISIONS}}  # fmt: skip
    return {
        "reference": f"mslam_ref.{k.name}",
        "tolerance_group": k.group,
        "signature": k.signature,
        "outputs": outputs,
    }


def _describe(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    return {n: {"shape": list(a.shape), "dtype": a.dtype.str} for n, a in arrays.items()}


def write_golden_set(folder: str | Path) -> dict[str, Any]:
    """Build every case, run the reference on it and write the golden set into ``folder``.

    Args:
        folder: an existing (empty) folder.

    Returns:
        A summary: number of kernels, cases and bytes written.
    """
    folder = Path(folder)
    from mslam import __version__

    entries, total = [], 0
    for case in build_cases():
        kernel = KERNELS[case.kernel]
        ins = {n: _canonical(a) for n, a in case.inputs.items()}  # what the file will hold
        outs = reference_outputs(kernel, dataclasses.replace(case, inputs=ins))
        # Any: numpy's stub of savez types **kwds so that a dict of arrays also meets allow_pickle
        arrays: dict[str, Any] = {f"in.{n}": a for n, a in ins.items()}
        arrays |= {f"out.{n}": a for n, a in outs.items()}
        rel = f"{case.kernel}/{case.name}.npz"
        (folder / case.kernel).mkdir(exist_ok=True)
        np.savez(folder / rel, **arrays)  # stored (uncompressed) entries
        total += (folder / rel).stat().st_size
        entries.append({"kernel": case.kernel, "name": case.name, "file": rel,
                        "note": case.note, "precisions": list(case.precisions), "params": case.params,
                        "arrays": _describe(arrays)})  # fmt: skip
    index = {
        "format": FORMAT,
        "version": VERSION,
        "generated_by": f"mslam {__version__} (reference outputs from mslam_ref)",
        "conventions": CONVENTIONS,
        "files": "KERNEL/CASE.npz: zip archive of stored (uncompressed) .npy v1.0 entries "
        "'in.NAME.npy' (kernel inputs) and 'out.NAME.npy' (reference outputs)",
        "measures": MEASURES,
        "kernels": {name: _kernel_entry(k) for name, k in KERNELS.items()},
        "cases": entries,
    }
    text = json.dumps(index, indent=1, allow_nan=False) + "\n"
    (folder / "index.json").write_text(text)
    total += len(text)
    return {"kernels": len({e["kernel"] for e in entries}), "cases": len(entries), "bytes": total}
