"""Bundle adjustment — file formats: BAL problems and g2o SE(3) pose graphs.

* BAL (Agarwal et al., "Bundle Adjustment in the Large", ECCV 2010)::

      <num_cameras> <num_points> <num_observations>
      <camera_index> <point_index> <x> <y>      (num_observations lines)
      <9 camera parameters per camera>          (one value per line, or several)
      <3 coordinates per point>

* g2o 3-D pose graph: ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and
  ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 upper-triangular, row-major entries of the
  6x6 information matrix in the order (x, y, z, rx, ry, rz).

A malformed file raises ``ValueError("<file>:<line>: <what>")``.

Public functions, in reading order: read_bal, write_bal, PoseGraph, read_g2o_se3, write_g2o_se3.

Upstream: Ceres examples/bal_problem.cc (BALProblem::LoadFile, written from the format); g2o
types/slam3d vertex_se3.cpp / edge_se3.cpp (read/write).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from mslam_ref.ba.problem import BALProblem
from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["PoseGraph", "format_bal", "read_bal", "read_g2o_se3", "write_bal", "write_g2o_se3"]


def _numbers(lines: list[str], start: int, count: int, path: Path, what: str) -> FloatArray:
    """Parse exactly ``count`` floats from ``lines[start:]`` (any layout) and nothing after them.

    Errors name the file and line: a bad or non-finite number, an early end of file, values
    beyond ``count`` (a header that claims fewer observations, cameras or points than the file
    holds, or trailing data).
    """
    vals: list[float] = []
    i = start
    while len(vals) < count:
        if i >= len(lines):
            raise ValueError(
                f"{path}:{i}: file ends after {len(vals)} of {count} {what} (header counts?)"
            )
        for tok in lines[i].split():
            try:
                v = float(tok)
            except ValueError:
                raise ValueError(f"{path}:{i + 1}: bad number {tok!r} in {what}") from None
            if not np.isfinite(v):
                raise ValueError(f"{path}:{i + 1}: non-finite value {tok!r} in {what}")
            vals.append(v)
        i += 1
    extra = len(vals) > count
    rest = next((k for k in range(i, len(lines)) if lines[k].strip()), None)
    if extra or rest is not None:
        line = i if extra or rest is None else rest + 1
        raise ValueError(
            f"{path}:{line}: more values than the header's counts allow ({count} {what}); "
            "the header does not match the file or there is trailing data"
        )
    return np.asarray(vals)


def read_bal(path: str | Path) -> BALProblem:
    """Read a BAL problem file.

    Args:
        path: the ``problem-*.txt`` file.

    Returns:
        A :class:`~mslam_ref.ba.problem.BALProblem` (cameras (M, 9), points (P, 3), obs_cam (O,),
        obs_pt (O,), obs (O, 2)).

    Raises:
        ValueError: ``"<path>:<line>: ..."`` on a malformed header, observation or parameter.
        FileNotFoundError: when the file does not exist.
    """
    path = Path(path)
    lines = path.read_text().splitlines()
    if not lines:
        raise ValueError(f"{path}:1: empty file")
    head = lines[0].split()
    try:
        M, P, O = (int(x) for x in head)
    except ValueError:
        raise ValueError(f"{path}:1: header must be three integers, got {lines[0]!r}") from None
    if M <= 0 or P <= 0 or O <= 0:
        raise ValueError(f"{path}:1: counts must be positive, got {M} {P} {O}")
    if len(lines) < 1 + O:
        raise ValueError(f"{path}:{len(lines)}: file ends inside the observations")
    obs_cam = np.empty(O, np.int64)
    obs_pt = np.empty(O, np.int64)
    obs = np.empty((O, 2))
    for k in range(O):
        tok = lines[1 + k].split()
        try:
            if len(tok) != 4:
                raise ValueError
            obs_cam[k], obs_pt[k] = int(tok[0]), int(tok[1])
            obs[k] = float(tok[2]), float(tok[3])
            if not np.all(np.isfinite(obs[k])):
                raise ValueError
        except ValueError:
            raise ValueError(
                f"{path}:{k + 2}: expected '<camera> <point> <x> <y>' (finite numbers), "
                f"got {lines[1 + k]!r}"
            ) from None
        if not (0 <= obs_cam[k] < M and 0 <= obs_pt[k] < P):
            raise ValueError(f"{path}:{k + 2}: camera or point index out of range")
    vals = _numbers(lines, 1 + O, 9 * M + 3 * P, path, "camera and point parameters")
    if not np.all(np.isfinite(obs)):
        raise ValueError(f"{path}: non-finite observation")
    cams = vals[: 9 * M].reshape(M, 9)
    pts = vals[9 * M :].reshape(P, 3)
    return BALProblem(cameras=cams, points=pts, obs_cam=obs_cam, obs_pt=obs_pt, obs=obs)


def write_bal(problem: BALProblem, path: str | Path) -> None:
    """Write a BAL problem (full double precision, one parameter per line).

    Args:
        problem: the problem (e.g. ``LMResult.problem`` after a solve).
        path: output file.
    """
    Path(path).write_text(format_bal(problem))


def format_bal(problem: BALProblem) -> str:
    """The text of a BAL file (:func:`write_bal`); ``ValueError`` on a non-finite value."""
    for name in ("cameras", "points", "obs"):
        if not np.all(np.isfinite(getattr(problem, name))):
            raise ValueError(f"problem.{name}: non-finite value; refusing to write a BAL file")
    M, P, O = len(problem.cameras), len(problem.points), len(problem.obs_cam)
    out = [f"{M} {P} {O}"]
    out += [
        f"{c} {p} {x:.17g} {y:.17g}"
        for c, p, (x, y) in zip(problem.obs_cam.tolist(), problem.obs_pt.tolist(), problem.obs)
    ]
    out += [f"{v:.17g}" for v in problem.cameras.reshape(-1).tolist()]
    out += [f"{v:.17g}" for v in problem.points.reshape(-1).tolist()]
    return "\n".join(out) + "\n"


@dataclasses.dataclass(frozen=True, eq=False)
class PoseGraph:
    """An SE(3) pose graph (g2o ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``).

    Attributes:
        ids: (N,) int vertex ids as written in the file.
        poses: (N, 7) ``[t, q_xyzw]`` (vertex to world, g2o ``VertexSE3``).
        edge_i: (E,) int vertex *indices* (rows of ``poses``) of the edge's first vertex.
        edge_j: (E,) int indices of the second vertex.
        measurements: (E, 7) relative pose ``Z_ij ~ X_i^-1 X_j``.
        information: (E, 6, 6) symmetric information, order (x, y, z, rx, ry, rz).
    """

    ids: IntArray
    poses: FloatArray
    edge_i: IntArray
    edge_j: IntArray
    measurements: FloatArray
    information: FloatArray


def _floats(tok: list[str], n: int, path: Path, lineno: int, tag: str) -> list[float]:
    if len(tok) != n:
        raise ValueError(f"{path}:{lineno}: {tag} expects {n} values, got {len(tok)}")
    try:
        vals = [float(x) for x in tok]
    except ValueError:
        raise ValueError(f"{path}:{lineno}: bad number in {tag}") from None
    if not all(np.isfinite(vals)):
        raise ValueError(f"{path}:{lineno}: non-finite value in {tag}")
    if n == 7 and not np.linalg.norm(vals[3:]) > 1e-12:
        raise ValueError(f"{path}:{lineno}: quaternion of zero length in {tag}")
    return vals


def read_g2o_se3(path: str | Path) -> PoseGraph:
    """Read a g2o 3-D pose graph (``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``; ``FIX`` lines ignored).

    Raises:
        ValueError: ``"<path>:<line>: ..."`` on an unknown tag, a wrong value count, a bad
            number, a duplicate vertex id or an edge to an unknown vertex.
    """
    path = Path(path)
    ids: list[int] = []
    poses: list[list[float]] = []
    edges: list[tuple[int, int, int]] = []
    meas: list[list[float]] = []
    infos: list[list[float]] = []
    index: dict[int, int] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        tag = tok[0]
        if tag == "VERTEX_SE3:QUAT":
            if len(tok) != 9:
                raise ValueError(f"{path}:{lineno}: {tag} expects 8 values, got {len(tok) - 1}")
            try:
                vid = int(tok[1])
            except ValueError:
                raise ValueError(f"{path}:{lineno}: bad vertex id {tok[1]!r}") from None
            if vid in index:
                raise ValueError(f"{path}:{lineno}: duplicate vertex id {vid}")
            index[vid] = len(ids)
            ids.append(vid)
            poses.append(_floats(tok[2:], 7, path, lineno, tag))
        elif tag == "EDGE_SE3:QUAT":
            if len(tok) != 31:
                raise ValueError(f"{path}:{lineno}: {tag} expects 30 values, got {len(tok) - 1}")
            try:
                i, j = int(tok[1]), int(tok[2])
            except ValueError:
                raise ValueError(f"{path}:{lineno}: bad vertex id in {tag}") from None
            edges.append((i, j, lineno))
            meas.append(_floats(tok[3:10], 7, path, lineno, tag))
            infos.append(_floats(tok[10:], 21, path, lineno, tag))
        elif tag == "FIX":
            continue
        else:
            raise ValueError(f"{path}:{lineno}: unknown record {tag!r}")
    for i, j, lineno in edges:
        for v in (i, j):
            if v not in index:
                raise ValueError(f"{path}:{lineno}: edge refers to unknown vertex {v}")
    iu = np.triu_indices(6)
    info = np.zeros((len(infos), 6, 6))
    if infos:
        info[:, iu[0], iu[1]] = np.asarray(infos)
        info = info + np.triu(info, 1).transpose(0, 2, 1)
    P = np.asarray(poses, dtype=np.float64).reshape(-1, 7)
    Z = np.asarray(meas, dtype=np.float64).reshape(-1, 7)
    for arr in (P, Z):
        arr[:, 3:] /= np.linalg.norm(arr[:, 3:], axis=-1, keepdims=True)
    return PoseGraph(
        ids=np.asarray(ids, np.int64),
        poses=P,
        edge_i=np.asarray([index[i] for i, _, _ in edges], np.int64),
        edge_j=np.asarray([index[j] for _, j, _ in edges], np.int64),
        measurements=Z,
        information=info,
    )


def write_g2o_se3(graph: PoseGraph, path: str | Path) -> None:
    """Write a pose graph in the g2o 3-D format read by :func:`read_g2o_se3`."""
    out = []
    for vid, p in zip(graph.ids.tolist(), graph.poses.tolist()):
        out.append("VERTEX_SE3:QUAT " + " ".join([str(vid)] + [f"{v:.17g}" for v in p]))
    iu = np.triu_indices(6)
    for i, j, z, inf in zip(graph.edge_i, graph.edge_j, graph.measurements, graph.information):
        vals = [f"{v:.17g}" for v in [*z.tolist(), *inf[iu].tolist()]]
        out.append(f"EDGE_SE3:QUAT {graph.ids[i]} {graph.ids[j]} " + " ".join(vals))
    Path(path).write_text("\n".join(out) + "\n")
