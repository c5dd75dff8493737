"""Paper §4 / upstream outputs — trajectory and point-cloud files (docs/upstream.md §13).

What a run writes and what the evaluation reads:

* **TUM trajectories** ``timestamp tx ty tz qx qy qz qw`` (one pose per line, camera-to-world
  ``T_WC`` with the Sim(3) scale dropped, quaternion in xyzw order) — the format of upstream's
  ``evaluate.save_traj`` and of every ground truth the paper is scored against;
* **KITTI poses**: the first three rows of the 4x4 ``T_WC`` per line (12 numbers, row-major);
* **EuRoC ground-truth csv** (``state_groundtruth_estimate0/data.csv``): ``ns, x, y, z, qw, qx,
  qy, qz, ...``, converted the way evo converts it (``stamp_ns / 1e9`` in float64, quaternion
  rolled to xyzw);
* **PLY point clouds** (:mod:`mslam.ply`, re-exported here): written binary little-endian,
  vertex ``x y z`` float32 + ``red green blue`` uchar, upstream's ``save_ply`` layout; read
  also as ASCII or big-endian, with or without colours.

Writers go through :func:`mslam.atomic.write_atomic` (temporary file + rename), so an
error never leaves a partial file. Readers raise ``ValueError("<file>:<line>: <what>")`` on a
malformed line and ``FileNotFoundError`` on a missing file.

Public functions, in reading order:
    write_tum, read_tum, read_kitti, read_euroc_csv, read_trajectory, write_ply, read_ply

Upstream: mast3r_slam/evaluate.py (save_traj, save_reconstruction, save_ply); evo
evo/tools/file_interface.py (read_tum_trajectory_file, read_kitti_poses_file,
read_euroc_csv_trajectory) — formats re-implemented from their description, no code copied.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mslam.atomic import write_atomic
from mslam.ply import read_ply, write_ply
from mslam_ref import so3
from mslam_ref.conventions import FloatArray, as_float_array

__all__ = [
    "read_euroc_csv",
    "read_kitti",
    "read_ply",
    "read_trajectory",
    "read_tum",
    "write_ply",
    "write_tum",
]


def _num(x: float) -> str:
    """Shortest text that parses back to the same float64 (Python's repr)."""
    return repr(float(x))


def _poses_to_tq(T_WC: Any) -> FloatArray:
    """(n, 7) ``[t, q_xyzw]`` from (n, 8) Sim(3), (n, 7) ``[t, q]`` or (n, 4, 4) matrices."""
    arr = np.asarray(T_WC, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] in ((4, 4), (3, 4)):
        M = as_float_array(arr, "T_WC")
        sR = M[:, :3, :3]
        det = np.linalg.det(sR)
        if np.any(det <= 0.0):
            raise ValueError("T_WC: the 3x3 block of every matrix must be a scaled rotation")
        q = so3.from_matrix(sR / np.cbrt(det)[:, None, None])
        return np.concatenate([M[:, :3, 3], q], axis=1)
    if arr.ndim == 2 and arr.shape[1] in (7, 8):
        arr = as_float_array(arr, "T_WC")
        return np.concatenate([arr[:, :3], so3.normalize(arr[:, 3:7], "T_WC")], axis=1)
    raise ValueError(f"T_WC: expected shape (n, 8), (n, 7) or (n, 4, 4), got {arr.shape}")


def write_tum(path: str | Path, timestamps: Any, T_WC: Any) -> None:
    """Write a TUM trajectory ``timestamp tx ty tz qx qy qz qw``, camera-to-world, atomically.

    Upstream: mast3r_slam/evaluate.py::save_traj (keyframe poses, ``as_SE3`` drops the scale).

    Args:
        path: output file (parent folders are created).
        timestamps: (n,) float seconds, or (n,) strings written verbatim (e.g. EuRoC's
            nanosecond stamps); each must parse as a finite float.
        T_WC: (n, 8) Sim(3) ``[t, q_xyzw, s]`` (scale dropped), (n, 7) ``[t, q_xyzw]`` or
            (n, 4, 4) matrices ``[[sR, t], [0, 1]]`` (the scale is divided out of the rotation).

    Numbers are written with the shortest repr that reads back to the same float64, so
    ``read_tum(write_tum(...))`` round-trips exactly (quaternions are normalised).

    Raises:
        ValueError: on mismatched lengths, bad shapes, non-finite values or bad stamps.
    """
    tq = _poses_to_tq(T_WC)
    stamps = np.asarray(timestamps)
    if stamps.ndim != 1 or len(stamps) != len(tq):
        raise ValueError(
            f"timestamps: expected shape ({len(tq)},) to match T_WC, got {stamps.shape}"
        )
    if stamps.dtype.kind in "USO":
        texts = [str(s).strip() for s in stamps.tolist()]
        for s in texts:
            try:
                ok = np.isfinite(float(s)) and len(s.split()) == 1
            except ValueError:
                ok = False
            if not ok:
                raise ValueError(f"timestamps: {s!r} is not a finite number")
    else:
        st = as_float_array(stamps, "timestamps")
        texts = [_num(s) for s in st.tolist()]
    lines = [" ".join([s, *(_num(v) for v in row)]) for s, row in zip(texts, tq.tolist())]
    write_atomic(path, "".join(line + "\n" for line in lines))


def _read_rows(
    path: Path, ncols: int, what: str, delim: str | None = None, names: tuple[str, ...] = ()
) -> tuple[FloatArray, list[int]]:
    """Parse a numeric table skipping ``#`` comments and blank lines; errors name file and line.

    Args:
        path: the file.
        ncols: exact number of columns, or ``-ncols`` for "at least ncols" (only the first
            ``ncols`` are kept).
        what: format name for error messages.
        delim: column separator (None = any whitespace).
        names: column names, to name a non-finite value's column in the error.

    Returns:
        (rows (n, |ncols|) float64, line numbers (n,)).
    """
    text = path.read_text()
    need = abs(ncols)
    rows: list[list[float]] = []
    linenos: list[int] = []
    for k, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tok = [t.strip() for t in line.split(delim)] if delim else line.split()
        if (ncols > 0 and len(tok) != need) or len(tok) < need:
            exact = "" if ncols > 0 else "at least "
            raise ValueError(
                f"{path}:{k}: {what} lines need {exact}{need} numbers, got {len(tok)}: {raw!r}"
            )
        try:
            vals = [float(t) for t in tok[:need]]
        except ValueError:
            raise ValueError(f"{path}:{k}: not a number in {what} line: {raw!r}") from None
        if not all(np.isfinite(vals)):
            j = int(np.flatnonzero(~np.isfinite(vals))[0])
            col = names[j] if j < len(names) else f"value (column {j + 1})"
            raise ValueError(f"{path}:{k}: non-finite {col} in {what} line: {raw!r}")
        rows.append(vals)
        linenos.append(k)
    if not rows:
        raise ValueError(f"{path}: no {what} poses in file")
    return np.asarray(rows, dtype=np.float64), linenos


def _check_quats(path: Path, q: FloatArray, linenos: list[int]) -> None:
    """Reject zero quaternions (they have no rotation); errors name the line."""
    bad = np.flatnonzero(np.linalg.norm(q, axis=1) < 1e-12)
    if bad.size:
        raise ValueError(f"{path}:{linenos[bad[0]]}: quaternion has zero norm")


#: The columns of a TUM trajectory line.
TUM_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")


def read_tum(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Read a TUM trajectory file.

    Lines ``timestamp tx ty tz qx qy qz qw`` separated by whitespace; ``#`` comments and blank
    lines are skipped; any float syntax (``1.4e+09``) is accepted. Quaternions are returned as
    written (not normalised).

    Args:
        path: the file.

    Returns:
        timestamps (n,) float64 and poses (n, 7) ``[tx, ty, tz, qx, qy, qz, qw]``.

    Raises:
        ValueError: ``"<file>:<line>: ..."`` on a line without exactly 8 finite numbers or with
            a zero quaternion, or when the file has no pose.
        FileNotFoundError: when the file does not exist.
    """
    path = Path(path)
    rows, linenos = _read_rows(path, 8, "TUM", names=TUM_COLUMNS)
    _check_quats(path, rows[:, 4:8], linenos)
    return rows[:, 0].copy(), rows[:, 1:8].copy()


def read_kitti(path: str | Path) -> FloatArray:
    """Read a KITTI odometry pose file (12 numbers per line: the 3x4 top of ``T_WC``).

    Args:
        path: the file.

    Returns:
        (n, 4, 4) float64 pose matrices with last row ``[0, 0, 0, 1]``.

    Raises:
        ValueError: ``"<file>:<line>: ..."`` on a line without exactly 12 finite numbers.
        FileNotFoundError: when the file does not exist.
    """
    path = Path(path)
    rows, _ = _read_rows(path, 12, "KITTI")
    M = np.zeros((len(rows), 4, 4))
    M[:, :3, :] = rows.reshape(-1, 3, 4)
    M[:, 3, 3] = 1.0
    return M


def read_euroc_csv(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Read an EuRoC MAV ground-truth csv the way evo converts it (``evo_traj euroc``).

    Rows ``timestamp_ns, px, py, pz, qw, qx, qy, qz[, more columns]``, comma separated, ``#``
    header lines skipped. The stamp is parsed as a float64 and divided by 1e9 (exactly evo's
    conversion, so association against evo's TUM export is bit-identical); the quaternion is
    reordered from wxyz to xyzw.

    Args:
        path: ``mav0/state_groundtruth_estimate0/data.csv`` or any csv with >= 8 columns.

    Returns:
        timestamps (n,) seconds and poses (n, 7) ``[tx, ty, tz, qx, qy, qz, qw]``.

    Raises:
        ValueError: ``"<file>:<line>: ..."`` on a short or non-numeric row.
        FileNotFoundError: when the file does not exist.
    """
    path = Path(path)
    rows, linenos = _read_rows(path, -8, "EuRoC csv", delim=",")
    _check_quats(path, rows[:, 4:8], linenos)
    stamps = np.divide(rows[:, 0], 1e9)
    q_xyzw = rows[:, [5, 6, 7, 4]]
    return stamps, np.concatenate([rows[:, 1:4], q_xyzw], axis=1)


def read_trajectory(path: str | Path) -> tuple[FloatArray | None, FloatArray]:
    """Read a trajectory in TUM, KITTI or EuRoC-csv format, detected from the content.

    A ``.csv`` file or a first data line with commas is EuRoC csv; otherwise 8 numbers per line
    is TUM and 12 is KITTI.

    Args:
        path: the file.

    Returns:
        timestamps (n,) seconds, or None for KITTI (no stamps: associate by index), and
        poses (n, 7) ``[t, q_xyzw]``.

    Raises:
        ValueError: naming the file when the format is not recognised or a line is malformed.
        FileNotFoundError: when the file does not exist.
    """
    path = Path(path)
    first = None
    with path.open() as fh:
        for k, raw in enumerate(fh, start=1):
            line = raw.strip()
            if line and not line.startswith("#"):
                first = (k, line)
                break
    if first is None:
        raise ValueError(f"{path}: no poses in file (empty or only comments)")
    k, line = first
    if path.suffix.lower() == ".csv" or "," in line:
        return read_euroc_csv(path)
    n = len(line.split())
    if n == 8:
        return read_tum(path)
    if n == 12:
        M = read_kitti(path)
        return None, np.concatenate([M[:, :3, 3], so3.from_matrix(M[:, :3, :3])], axis=1)
    raise ValueError(
        f"{path}:{k}: unknown trajectory format: {n} columns (TUM has 8, KITTI 12, EuRoC csv "
        "uses commas)"
    )
