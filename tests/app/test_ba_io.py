"""BAL and g2o SE(3) IO: round trips, malformed files name the file and the line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tolerances import F64_COPY

from mslam import bal as io
from mslam_ref.ba import synthetic


def test_bal_round_trip(tmp_path: Path) -> None:
    p, _ = synthetic.make_bal_problem(n_cams=3, n_points=7)
    f = tmp_path / "p.txt"
    io.write_bal(p, f)
    q = io.read_bal(f)
    for a in ("cameras", "points", "obs_cam", "obs_pt", "obs"):
        np.testing.assert_array_equal(getattr(q, a), getattr(p, a))


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("2 2\n", 1),
        ("1 1 1\n0 0 1.0\n" + "0\n" * 12, 2),
        ("1 1 1\n0 5 1.0 2.0\n" + "0\n" * 12, 2),
        ("1 1 1\n0 0 1.0 2.0\n" + "0\n" * 5 + "abc\n" + "0\n" * 6, 8),
        ("1 1 1\n0 0 1.0 2.0\n" + "0\n" * 5, 7),
    ],
)
def test_bal_malformed(tmp_path: Path, text: str, line: int) -> None:
    f = tmp_path / "bad.txt"
    f.write_text(text)
    with pytest.raises(ValueError, match=rf"bad\.txt:{line}:"):
        io.read_bal(f)


def _graph_text() -> str:
    info = " ".join(
        ["1"] + ["0"] * 5 + ["1"] + ["0"] * 4 + ["1"] + ["0"] * 3 + ["1", "0", "0", "1", "0", "1"]
    )
    return (
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
        "VERTEX_SE3:QUAT 5 1 0 0 0 0 0.1736 0.9848\n"
        f"EDGE_SE3:QUAT 0 5 1 0 0 0 0 0.17 0.98 {info}\n"
    )


def test_g2o_round_trip(tmp_path: Path) -> None:
    f = tmp_path / "g.g2o"
    f.write_text(_graph_text())
    g = io.read_g2o_se3(f)
    assert g.ids.tolist() == [0, 5] and g.edge_j.tolist() == [1]
    np.testing.assert_allclose(g.information[0], np.eye(6))
    io.write_g2o_se3(g, tmp_path / "h.g2o")
    h = io.read_g2o_se3(tmp_path / "h.g2o")
    np.testing.assert_allclose(h.poses, g.poses, atol=F64_COPY)
    np.testing.assert_allclose(h.measurements, g.measurements, atol=F64_COPY)
    np.testing.assert_array_equal(h.information, g.information)


@pytest.mark.parametrize(
    ("bad", "line", "what"),
    [
        ("VERTEX_SE3:QUAT 7 0 0 0 0 0 1\n", 4, "expects 8"),
        ("EDGE_SE3:QUAT 0 9 " + "0 " * 6 + "1 " + "1 " * 21 + "\n", 4, "unknown vertex 9"),
        ("VERTEX_XY 1 2 3\n", 4, "unknown record"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n", 4, "duplicate"),
        ("VERTEX_SE3:QUAT 8 0 0 x 0 0 0 1\n", 4, "bad number"),
    ],
)
def test_g2o_malformed(tmp_path: Path, bad: str, line: int, what: str) -> None:
    f = tmp_path / "bad.g2o"
    f.write_text(_graph_text() + bad)
    with pytest.raises(ValueError, match=rf"bad\.g2o:{line}: .*{what}"):
        io.read_g2o_se3(f)


def test_parking_garage_loads(shared_data: Path) -> None:
    g = io.read_g2o_se3(shared_data / "ba" / "parking-garage.g2o")
    assert len(g.ids) == 1661 and len(g.edge_i) == 6275
    np.testing.assert_allclose(g.information, g.information.transpose(0, 2, 1))
