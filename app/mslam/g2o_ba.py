"""g2o bundle-adjustment files (SE(3) poses, XYZ points, monocular and stereo projections).

The records are g2o's file tags of ``types_six_dof_expmap`` and ``types_sba`` / ``slam3d``:

    PARAMS_CAMERAPARAMETERS id f cx cy baseline        pinhole camera, fx = fy = f, bf = f b
    VERTEX_SE3:EXPMAP id tx ty tz qx qy qz qw          camera-to-world (g2o writes the inverse
                                                       of VertexSE3Expmap's world-to-camera)
    VERTEX_SBAPOINTXYZ id x y z                        a point (VERTEX_TRACKXYZ too)
    EDGE_PROJECT_XYZ2UV:EXPMAP point pose cam u v I00 I01 I11
    EDGE_PROJECT_XYZ2UVU:EXPMAP point pose cam u v ur I00 I01 I02 I11 I12 I22
    FIX id                                             a fixed vertex

Each pose gets the camera of its edges (cuda-bundle-adjustment attaches the camera to the pose),
so all edges of one pose must name the same ``cam``. The information must be isotropic,
``omega I`` (cuda-bundle-adjustment's scalar information); ``omega`` is ``I00``.

Public names: read_g2o_ba, format_g2o_ba, write_g2o_ba.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mslam_ref import se3
from mslam_ref.ba.problem import PinholeProblem
from mslam_ref.ba.robust import RobustKernel

__all__ = ["format_g2o_ba", "read_g2o_ba", "write_g2o_ba"]

_COUNTS = {"PARAMS_CAMERAPARAMETERS": 5, "VERTEX_SE3:EXPMAP": 8, "VERTEX_SBAPOINTXYZ": 4,
           "VERTEX_TRACKXYZ": 4, "EDGE_PROJECT_XYZ2UV:EXPMAP": 8,
           "EDGE_PROJECT_XYZ2UVU:EXPMAP": 12, "FIX": 1}  # fmt: skip
_MONO, _STEREO = "EDGE_PROJECT_XYZ2UV:EXPMAP", "EDGE_PROJECT_XYZ2UVU:EXPMAP"


def _record(tok: list[str], path: Path, lineno: int) -> tuple[list[int], list[float]]:
    """The leading ids and the numbers of one record, checked."""
    tag = tok[0]
    if tag not in _COUNTS:
        raise ValueError(f"{path}:{lineno}: unknown record {tag!r}")
    if len(tok) - 1 != _COUNTS[tag]:
        raise ValueError(
            f"{path}:{lineno}: {tag} expects {_COUNTS[tag]} values, got {len(tok) - 1}"
        )
    n_ids = 3 if tag.startswith("EDGE") else 1
    try:
        ids = [int(t) for t in tok[1 : 1 + n_ids]]
        vals = [float(t) for t in tok[1 + n_ids :]]
    except ValueError:
        raise ValueError(f"{path}:{lineno}: bad number in {tag}") from None
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{path}:{lineno}: non-finite value in {tag}")
    return ids, vals


def _omega(tag: str, info: list[float], path: Path, lineno: int) -> float:
    """The scalar information of an isotropic upper-triangle ``info``."""
    n = 2 if tag == _MONO else 3
    I = np.zeros((n, n))
    I[np.triu_indices(n)] = info
    if not (I[0, 0] > 0.0 and np.allclose(I, I[0, 0] * np.eye(n), rtol=0.0, atol=0.0)):
        raise ValueError(f"{path}:{lineno}: information must be omega * I with omega > 0")
    return float(I[0, 0])


def _parse(path: Path):
    cams: dict[int, list[float]] = {}
    poses: dict[int, list[float]] = {}
    points: dict[int, list[float]] = {}
    edges: list[tuple[int, int, int, list[float], bool, float, int]] = []
    fixed: set[int] = set()
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        tag = tok[0]
        ids, vals = _record(tok, path, lineno)
        if tag == "PARAMS_CAMERAPARAMETERS":
            cams[ids[0]] = vals
        elif tag in ("VERTEX_SE3:EXPMAP", "VERTEX_SBAPOINTXYZ", "VERTEX_TRACKXYZ"):
            if ids[0] in poses or ids[0] in points:
                raise ValueError(f"{path}:{lineno}: duplicate vertex id {ids[0]}")
            (poses if tag == "VERTEX_SE3:EXPMAP" else points)[ids[0]] = vals
        elif tag == "FIX":
            fixed.add(ids[0])
        else:
            k = 2 if tag == _MONO else 3
            om = _omega(tag, vals[k:], path, lineno)
            edges.append((ids[0], ids[1], ids[2], vals[:k], tag == _STEREO, om, lineno))
    return cams, poses, points, edges, fixed


def read_g2o_ba(path: str | Path, robust: str = "none") -> tuple[PinholeProblem, dict]:
    """Read a g2o BA file into a ``PinholeProblem`` (world-to-camera poses, per-pose cameras).

    Args:
        path: the file.
        robust: "none", "huber" or "tukey", with cuda-bundle-adjustment's deltas
            (sqrt(5.991) mono, sqrt(7.815) stereo).

    Returns:
        (problem, ids): ids maps "poses" and "points" to the file's vertex ids (lists, in the
        problem's order) and "cams" to each pose's camera id.

    Raises:
        ValueError: ``"<path>:<line>: ..."`` on an unknown record, a wrong value count, a bad
            number, a duplicate id, an edge to an unknown vertex or camera, a pose seen through
            two cameras, or a non-isotropic information.
    """
    path = Path(path)
    cams, poses, points, edges, fixed = _parse(path)
    pose_ids, point_ids = sorted(poses), sorted(points)
    pi = {v: i for i, v in enumerate(pose_ids)}
    li = {v: i for i, v in enumerate(point_ids)}
    pose_cam: dict[int, int] = {}
    for lid, pid, cid, _m, _st, _om, lineno in edges:
        if lid not in li or pid not in pi or cid not in cams:
            raise ValueError(f"{path}:{lineno}: edge refers to an unknown point, pose or camera")
        if pose_cam.setdefault(pid, cid) != cid:
            raise ValueError(f"{path}:{lineno}: pose {pid} is seen through two cameras")
    K = np.zeros((len(pose_ids), 5))
    for i, v in enumerate(pose_ids):
        f, cx, cy, b = cams[pose_cam[v]] if v in pose_cam else (1.0, 0.0, 0.0, 0.0)
        K[i] = (f, f, cx, cy, f * b)
    T_cw = np.asarray([poses[v] for v in pose_ids], np.float64).reshape(-1, 7)
    T_cw[:, 3:] /= np.linalg.norm(T_cw[:, 3:], axis=-1, keepdims=True)
    meas = np.zeros((len(edges), 3))
    for e, (_l, _p, _c, m, _st, _om, _ln) in enumerate(edges):
        meas[e, : len(m)] = m
    deltas = {"mono": np.sqrt(5.991), "stereo": np.sqrt(7.815)}
    problem = PinholeProblem(
        poses=se3.inv(T_cw), intrinsics=K,
        points=np.asarray([points[v] for v in point_ids], np.float64).reshape(-1, 3),
        obs_cam=np.asarray([pi[e[1]] for e in edges], np.int64),
        obs_pt=np.asarray([li[e[0]] for e in edges], np.int64), meas=meas,
        is_stereo=np.asarray([e[4] for e in edges], bool),
        information=np.asarray([e[5] for e in edges], np.float64),
        pose_fixed=np.asarray([v in fixed for v in pose_ids], bool),
        point_fixed=np.asarray([v in fixed for v in point_ids], bool),
        kernel_mono=RobustKernel(robust, deltas["mono"]),
        kernel_stereo=RobustKernel(robust, deltas["stereo"]),
    )  # fmt: skip
    return problem, {"poses": pose_ids, "points": point_ids,
                     "cams": [pose_cam.get(v, -1) for v in pose_ids]}  # fmt: skip


def write_g2o_ba(problem: PinholeProblem, ids: dict, path: str | Path) -> None:
    """Write :func:`format_g2o_ba` to ``path``."""
    Path(path).write_text(format_g2o_ba(problem, ids))


def format_g2o_ba(problem: PinholeProblem, ids: dict) -> str:
    """``problem`` in the format of :func:`read_g2o_ba` (one camera record per distinct
    intrinsics row; fx is written as f, so fx must equal fy); ``ids`` as it returns them."""
    out: list[str] = []
    cam_of: dict[tuple[float, ...], int] = {}
    pose_fixed, point_fixed = problem.pose_fixed, problem.point_fixed
    information, is_stereo = problem.information, problem.is_stereo
    # PinholeProblem.__post_init__ fills every optional array
    assert pose_fixed is not None and point_fixed is not None
    assert information is not None and is_stereo is not None
    for row in map(tuple, problem.intrinsics.tolist()):
        if row not in cam_of:
            cam_of[row] = len(cam_of)
            f, _fy, cx, cy, bf = row
            out.append(f"PARAMS_CAMERAPARAMETERS {cam_of[row]} {f:.17g} {cx:.17g} {cy:.17g} "
                       f"{bf / f:.17g}")  # fmt: skip
    T_wc = se3.inv(problem.poses)
    for v, T in zip(ids["poses"], T_wc.tolist()):
        out.append("VERTEX_SE3:EXPMAP " + " ".join([str(v)] + [f"{x:.17g}" for x in T]))
    for v, X in zip(ids["points"], problem.points.tolist()):
        out.append(f"VERTEX_SBAPOINTXYZ {v} " + " ".join(f"{x:.17g}" for x in X))
    for i, v in enumerate(ids["poses"]):
        if pose_fixed[i]:
            out.append(f"FIX {v}")
    for j, v in enumerate(ids["points"]):
        if point_fixed[j]:
            out.append(f"FIX {v}")
    for e in range(len(problem.obs_cam)):
        c, p = int(problem.obs_cam[e]), int(problem.obs_pt[e])
        cid = cam_of[tuple(problem.intrinsics[c].tolist())]
        om = f"{information[e]:.17g}"
        head = f"{ids['points'][p]} {ids['poses'][c]} {cid}"
        if is_stereo[e]:
            m = " ".join(f"{x:.17g}" for x in problem.meas[e])
            out.append(f"{_STEREO} {head} {m} {om} 0 0 {om} 0 {om}")
        else:
            m = " ".join(f"{x:.17g}" for x in problem.meas[e, :2])
            out.append(f"{_MONO} {head} {m} {om} 0 {om}")
    return "\n".join(out) + "\n"
