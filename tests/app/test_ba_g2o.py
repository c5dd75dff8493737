"""g2o BA files (SE(3) + XYZ, mono and stereo projections): round trip, the solve from a file
equals the solve of the problem, malformed files name the file and the line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from tolerances import F64_SOLVE

from mslam.g2o_ba import read_g2o_ba, write_g2o_ba
from mslam_ref.ba import lm, synthetic


def _problem():
    p, _ = synthetic.make_pinhole_problem(n_cams=4, n_points=20, stereo_fraction=0.5, seed=2)
    return p


def test_round_trip(tmp_path: Path) -> None:
    p = _problem()
    ids = {"poses": [10 + i for i in range(4)], "points": [100 + j for j in range(20)]}
    f = tmp_path / "ba.g2o"
    write_g2o_ba(p, ids, f)
    q, qids = read_g2o_ba(f)
    assert qids["poses"] == ids["poses"] and qids["points"] == ids["points"]
    np.testing.assert_allclose(q.poses, p.poses, rtol=0, atol=F64_SOLVE)
    for a in ("intrinsics", "points", "information"):
        np.testing.assert_allclose(getattr(q, a), getattr(p, a), rtol=0, atol=F64_SOLVE)
    st = p.is_stereo  # ur is stored for stereo edges only
    np.testing.assert_allclose(q.meas[:, :2], p.meas[:, :2], rtol=0, atol=F64_SOLVE)
    np.testing.assert_allclose(q.meas[st], p.meas[st], rtol=0, atol=F64_SOLVE)
    for a in ("obs_cam", "obs_pt", "is_stereo", "pose_fixed", "point_fixed"):
        np.testing.assert_array_equal(getattr(q, a), getattr(p, a))
    assert q.is_stereo.any() and not q.is_stereo.all()


def test_solve_from_file_equals_solve(tmp_path: Path) -> None:
    p = _problem()
    f = tmp_path / "ba.g2o"
    write_g2o_ba(p, {"poses": list(range(4)), "points": list(range(4, 24))}, f)
    q, _ = read_g2o_ba(f, robust="huber")
    cfg = lm.LMConfig(iterations=5)
    a = lm.optimize(q, cfg)
    assert q.kernel_mono.kind == "huber" and q.kernel_stereo.delta == pytest.approx(np.sqrt(7.815))
    assert a.final_cost < a.initial_cost
    b = lm.optimize(dataclasses.replace(p, kernel_mono=q.kernel_mono,
                                        kernel_stereo=q.kernel_stereo), cfg)  # fmt: skip
    np.testing.assert_allclose(a.final_cost, b.final_cost, rtol=F64_SOLVE)


GOOD = (
    "PARAMS_CAMERAPARAMETERS 0 500 320 240 0.1\n"
    "VERTEX_SE3:EXPMAP 1 0 0 0 0 0 0 1\n"
    "VERTEX_SBAPOINTXYZ 2 0 0 5\n"
)


@pytest.mark.parametrize(
    ("extra", "what"),
    [
        ("EDGE_PROJECT_XYZ2UV:EXPMAP 2 1 0 320 240 1 0\n", "expects 8 values"),
        ("EDGE_PROJECT_XYZ2UV:EXPMAP 2 1 0 320 x 1 0 1\n", "bad number"),
        ("EDGE_PROJECT_XYZ2UV:EXPMAP 2 1 0 320 240 1 0.5 1\n", "omega \\* I"),
        ("EDGE_PROJECT_XYZ2UV:EXPMAP 2 9 0 320 240 1 0 1\n", "unknown point, pose or camera"),
        ("VERTEX_SBAPOINTXYZ 1 0 0 1\n", "duplicate vertex id 1"),
        ("EDGE_SE3:QUAT 1 2\n", "unknown record"),
    ],
)
def test_malformed(tmp_path: Path, extra: str, what: str) -> None:
    f = tmp_path / "bad.g2o"
    f.write_text(GOOD + extra)
    with pytest.raises(ValueError, match=rf"bad\.g2o:4: .*{what}"):
        read_g2o_ba(f)
