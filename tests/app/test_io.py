"""Trajectory and point-cloud files (mslam.formats): round trips, malformed input, atomic writes."""

from __future__ import annotations

import re
import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from tolerances import F64_COPY, F64_IDENTITY

from mslam import formats as io
from mslam.ply import GREY
from mslam_ref import sim3


def _poses(rng: np.random.Generator, n: int, scale: bool = True) -> np.ndarray:
    xi = rng.normal(0, 1, (n, 7))
    if not scale:
        xi[:, 6] = 0.0
    return sim3.exp(xi)


@given(seed=st.integers(0, 10_000), n=st.integers(1, 20))
def test_tum_round_trip_is_exact_and_drops_scale(tmp_path_factory, seed, n) -> None:
    rng = np.random.default_rng(seed)
    T = _poses(rng, n)
    stamps = 1.3e9 + np.cumsum(rng.uniform(1e-3, 1.0, n))
    path = tmp_path_factory.mktemp("tum") / "traj.txt"
    io.write_tum(path, stamps, T)
    t2, p2 = io.read_tum(path)
    np.testing.assert_array_equal(t2, stamps)
    np.testing.assert_array_equal(p2[:, :3], T[:, :3])
    np.testing.assert_allclose(p2[:, 3:], T[:, 3:7], atol=F64_COPY)
    # A (n, 4, 4) Sim(3) matrix writes the same pose with the scale divided out.
    io.write_tum(path, stamps, sim3.to_matrix(T))
    _, p3 = io.read_tum(path)
    np.testing.assert_allclose(p3[:, :3], T[:, :3], atol=F64_IDENTITY)
    q = p3[:, 3:] * np.sign(np.sum(p3[:, 3:] * T[:, 3:7], axis=1, keepdims=True))
    np.testing.assert_allclose(q, T[:, 3:7], atol=F64_IDENTITY)


def test_tum_line_format(tmp_path) -> None:
    path = tmp_path / "kf.txt"
    T = np.array([[1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 2.5]])
    io.write_tum(path, np.array([12.5]), T)
    assert path.read_text() == "12.5 1.0 2.0 3.0 0.0 0.0 0.0 1.0\n"
    io.write_tum(path, np.array(["1403715529112143517"]), T)  # string stamps verbatim
    assert path.read_text().split()[0] == "1403715529112143517"


def test_tum_reader_comments_blank_lines_scientific(tmp_path) -> None:
    path = tmp_path / "t.txt"
    path.write_text(
        "# timestamp tx ty tz qx qy qz qw\n\n"
        "1.403715529112143517e+09 -6.151e-02 4.8e-2 1 0 0 0 1\n"
        "   \n"
        "1403715530\t1  2  3 0 0 1 0\n"
    )
    t, p = io.read_tum(path)
    np.testing.assert_array_equal(t, [1.403715529112143517e09, 1403715530.0])
    np.testing.assert_array_equal(p[0], [-0.06151, 0.048, 1, 0, 0, 0, 1])
    assert p.shape == (2, 7)


@pytest.mark.parametrize(
    ("text", "line", "what"),
    [
        ("0 1 2 3 0 0 0 1\n1 2 3 0 0 0 1\n", 2, "8 numbers"),
        ("# c\n0 1 2 3 0 0 0 1 9\n", 2, "8 numbers"),
        ("0 1 2 3 0 0 0 1\n\n1 x 2 3 0 0 0 1\n", 3, "not a number"),
        ("0 1 2 nan 0 0 0 1\n", 1, "non-finite"),
        ("0 1 2 3 0 0 0 0\n", 1, "zero norm"),
    ],
)
def test_tum_reader_malformed_names_file_and_line(tmp_path, text, line, what) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"bad\.txt:{line}: .*{what}"):
        io.read_tum(path)


def test_tum_reader_empty_and_missing(tmp_path) -> None:
    (tmp_path / "e.txt").write_text("# only a comment\n\n")
    with pytest.raises(ValueError, match=re.escape("e.txt: no TUM poses")):
        io.read_tum(tmp_path / "e.txt")
    with pytest.raises(FileNotFoundError):
        io.read_tum(tmp_path / "missing.txt")


def test_write_tum_validation(tmp_path) -> None:
    T = _poses(np.random.default_rng(0), 3)
    with pytest.raises(ValueError, match="timestamps"):
        io.write_tum(tmp_path / "a.txt", np.arange(2.0), T)
    with pytest.raises(ValueError, match="T_WC"):
        io.write_tum(tmp_path / "a.txt", np.arange(3.0), T[:, :5])
    with pytest.raises(ValueError, match="timestamps"):
        io.write_tum(tmp_path / "a.txt", np.array([0.0, np.nan, 1.0]), T)
    with pytest.raises(ValueError, match="timestamps"):
        io.write_tum(tmp_path / "a.txt", np.array(["1", "2 3", "4"]), T)
    assert not list(tmp_path.iterdir())


def test_atomic_write_leaves_no_partial_file(tmp_path, monkeypatch) -> None:
    """An error while writing keeps the previous file intact and leaves no temporary file."""
    path = tmp_path / "traj.txt"
    T = _poses(np.random.default_rng(1), 4)
    io.write_tum(path, np.arange(4.0), T)
    before = path.read_bytes()

    import mslam.atomic as atomic

    real_replace = atomic.os.replace

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        io.write_tum(path, np.arange(4.0) + 10, T)
    with pytest.raises(OSError, match="disk full"):
        io.write_ply(tmp_path / "cloud.ply", np.zeros((5, 3)), np.zeros((5, 3), np.uint8))
    monkeypatch.setattr(atomic.os, "replace", real_replace)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traj.txt"]


def test_kitti_reader(tmp_path) -> None:
    T = sim3.to_matrix(_poses(np.random.default_rng(2), 5, scale=False))
    path = tmp_path / "k.txt"
    path.write_text("".join(" ".join(f"{v:.17g}" for v in M[:3].ravel()) + "\n" for M in T))
    np.testing.assert_array_equal(io.read_kitti(path), T)
    stamps, tq = io.read_trajectory(path)
    assert stamps is None
    np.testing.assert_allclose(tq[:, :3], T[:, :3, 3])
    path.write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=re.escape("k.txt:1: KITTI lines need 12")):
        io.read_kitti(path)


def test_euroc_csv_reader_converts_like_evo(tmp_path) -> None:
    path = tmp_path / "data.csv"
    path.write_text(
        "#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z, v_x\n"
        "1403715524907143168,0.5,2.0,0.97,0.1,0.7,-0.2,0.6,0.0\n"
        "1403715524912143104,0.6,2.1,0.98,1.0,0.0,0.0,0.0,0.0\n"
    )
    t, p = io.read_euroc_csv(path)
    np.testing.assert_array_equal(t, np.array([1403715524907143168.0, 1403715524912143104.0]) / 1e9)
    np.testing.assert_array_equal(p[0], [0.5, 2.0, 0.97, 0.7, -0.2, 0.6, 0.1])
    np.testing.assert_array_equal(p[1, 3:], [0, 0, 0, 1])
    _, p2 = io.read_trajectory(path)
    np.testing.assert_array_equal(p2, p)
    path.write_text("1,2,3\n")
    with pytest.raises(ValueError, match=re.escape("data.csv:1: EuRoC csv lines need at least 8")):
        io.read_euroc_csv(path)


def test_read_trajectory_unknown_format(tmp_path) -> None:
    path = tmp_path / "x.txt"
    path.write_text("1 2 3\n")
    with pytest.raises(ValueError, match=re.escape("x.txt:1: unknown trajectory format")):
        io.read_trajectory(path)


@given(seed=st.integers(0, 10_000), n=st.integers(0, 50))
def test_ply_round_trip(tmp_path_factory, seed, n) -> None:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 10, (n, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    path = tmp_path_factory.mktemp("ply") / "cloud.ply"
    io.write_ply(path, xyz, rgb)
    xyz2, rgb2 = io.read_ply(path)
    np.testing.assert_array_equal(xyz2, xyz)
    np.testing.assert_array_equal(rgb2, rgb)


def test_ply_layout_is_binary_little_endian_xyz_float_rgb_uchar(tmp_path) -> None:
    path = tmp_path / "c.ply"
    io.write_ply(path, np.array([[1.0, -2.0, 0.5]]), np.array([[255, 0, 7]]))
    data = path.read_bytes()
    head, body = data.split(b"end_header\n")
    assert head.decode().splitlines() == [
        "ply", "format binary_little_endian 1.0", "element vertex 1",
        "property float x", "property float y", "property float z",
        "property uchar red", "property uchar green", "property uchar blue",
    ]  # fmt: skip
    assert body == struct.pack("<fffBBB", 1.0, -2.0, 0.5, 255, 0, 7)


def test_ply_validation_and_malformed(tmp_path) -> None:
    with pytest.raises(ValueError, match="rgb"):
        io.write_ply(tmp_path / "a.ply", np.zeros((2, 3)), np.full((2, 3), 300))
    with pytest.raises(ValueError, match="rgb"):
        io.write_ply(tmp_path / "a.ply", np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="xyz"):
        io.write_ply(tmp_path / "a.ply", np.full((2, 3), np.inf), np.zeros((2, 3)))
    assert not list(tmp_path.iterdir())
    good = tmp_path / "g.ply"
    io.write_ply(good, np.zeros((4, 3)), np.zeros((4, 3)))
    (tmp_path / "t.ply").write_bytes(good.read_bytes()[:-5])
    with pytest.raises(ValueError, match=re.escape("t.ply: truncated")):
        io.read_ply(tmp_path / "t.ply")
    (tmp_path / "n.ply").write_bytes(b"not a ply")
    with pytest.raises(ValueError, match=re.escape("n.ply: not a PLY")):
        io.read_ply(tmp_path / "n.ply")
    (tmp_path / "a.ply").write_bytes(good.read_bytes().replace(b"binary_little_endian", b"ebcdic"))
    with pytest.raises(ValueError, match=re.escape("a.ply:2: unsupported PLY format")):
        io.read_ply(tmp_path / "a.ply")
    (tmp_path / "b.ply").write_bytes(good.read_bytes().replace(b"binary_little_endian", b"ascii"))
    with pytest.raises(ValueError, match=re.escape("b.ply: truncated PLY")):
        io.read_ply(tmp_path / "b.ply")
    face_first = b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
    (tmp_path / "f.ply").write_bytes(face_first + b"element vertex 0\nend_header\n")
    with pytest.raises(ValueError, match=re.escape("f.ply:3: the first element must be 'vertex'")):
        io.read_ply(tmp_path / "f.ply")
    (tmp_path / "x.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n"
    )
    with pytest.raises(ValueError, match=re.escape("x.ply: PLY vertices need x, y, z")):
        io.read_ply(tmp_path / "x.ply")


def test_ply_reads_ascii_without_colours_and_ignores_faces(tmp_path) -> None:
    """A ground-truth mesh from another tool: ASCII, normals, no colours, faces after the vertices."""
    text = (
        "ply\r\nformat ascii 1.0\r\ncomment from a scanner\r\nelement vertex 2\r\n"
        "property double x\r\nproperty double y\r\nproperty double z\r\nproperty float nx\r\n"
        "element face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
        "0.5 -1 2 0\r\n3 4.25 -5e-1 1\r\n3 0 1 1\r\n"
    )
    (tmp_path / "m.ply").write_text(text, newline="")
    xyz, rgb = io.read_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(xyz, np.array([[0.5, -1, 2], [3, 4.25, -0.5]], np.float32))
    np.testing.assert_array_equal(rgb, np.full((2, 3), GREY, np.uint8))


def test_ply_reads_big_endian_doubles_and_float_colours(tmp_path) -> None:
    xyz = np.array([[1.0, -2.0, 3.5], [1e-3, 7.0, -0.25]])
    colours = np.array([[1.0, 0.0, 0.5], [0.2, 0.4, 0.6]])
    dtype = [("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("nz", ">f4"),
             ("red", ">f4"), ("green", ">f4"), ("blue", ">f4")]  # fmt: skip
    v = np.zeros(2, dtype)
    v["x"], v["y"], v["z"] = xyz.T
    v["red"], v["green"], v["blue"] = colours.T
    head = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
        "property double y\nproperty double z\nproperty float nz\nproperty float red\n"
        "property float green\nproperty float blue\nend_header\n"
    )
    (tmp_path / "b.ply").write_bytes(head.encode() + v.tobytes())
    xyz2, rgb2 = io.read_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(xyz2, xyz.astype(np.float32))
    np.testing.assert_array_equal(rgb2, np.rint(colours * 255).astype(np.uint8))
