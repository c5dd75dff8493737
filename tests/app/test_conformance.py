"""``mslam conformance``: golden cases exported from the reference, checked against
implementations (the reference, the Taichi kernels, an adapter over another API, a planted
error), bad input, and the cases read by the C++ example program."""

from __future__ import annotations

import json
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
from tolerances import SHARE, TOL

from mslam.cli import main
from mslam.conformance.kernels import KERNELS
from mslam.conformance.tolerances import SHARE as CONF_SHARE
from mslam.conformance.tolerances import TOLERANCES

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples" / "conformance"
#: The golden set is meant to stay small (a few MB) so that tests and downloads stay quick.
MAX_BYTES = 4_000_000
#: Kernels of the golden set without a Taichi twin (finer-grained steps for porting).
REFERENCE_ONLY = {"tracking.ray_dist_residual_and_jacobian"}


@pytest.fixture(scope="module")
def golden(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("conformance") / "golden"
    assert main(["conformance", "export", str(out)]) == 0
    return out


def _check(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["conformance", "check", *args])
    out, err = capsys.readouterr()
    return rc, out, err


def _verdicts(table: str) -> dict[str, str]:
    """kernel -> verdict (last column) from the printed table."""
    rows = (line.split() for line in table.splitlines())
    return {r[0]: r[-1] for r in rows if r and r[0] in KERNELS}


def test_export_covers_every_kernel_with_edges_stored_uncompressed(golden: Path) -> None:
    index = json.loads((golden / "index.json").read_text())
    assert set(index["kernels"]) == set(KERNELS)
    assert "qx, qy, qz, qw" in index["conventions"]["sim3_element"]
    assert "left" in index["conventions"]["retraction"]
    cases = {(c["kernel"], c["name"]) for c in index["cases"]}
    assert {k for k, _ in cases} == set(KERNELS)
    for edge in [("sim3.exp", "edges"), ("sim3.log", "empty"), ("tracking.linearize", "empty"),
                 ("tracking.solve", "all_invalid"), ("matching.match", "bad_points"),
                 ("matching.iter_proj", "wavy"), ("backend.linearize", "empty"),
                 ("ba.cameras.bal_residuals", "empty")]:  # fmt: skip
        assert edge in cases
    for k in index["kernels"].values():
        for spec in k["outputs"].values():
            assert spec["measure"] in index["measures"] and "f64" in spec and "f32" in spec
    total = 0
    for c in index["cases"]:
        path = golden / c["file"]
        total += path.stat().st_size
        with zipfile.ZipFile(path) as z:
            assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
            assert {n.removesuffix(".npy") for n in z.namelist()} == set(c["arrays"])
    assert total < MAX_BYTES
    edges = np.load(golden / "sim3.exp" / "edges.npz")
    np.testing.assert_array_equal(edges["out.T"][0, 3:], [0.0, 0.0, 0.0, 1.0, 1.0])


def test_tolerances_are_the_parity_tolerances() -> None:
    """The app's conformance table repeats tests/tolerances.py (the app cannot import tests)."""
    for group, by_fp in TOLERANCES.items():
        for fp, (rtol, atol) in by_fp.items():
            assert TOL[(group, fp)] == {"rtol": rtol, "atol": atol}, (group, fp)
    # Matching shares: the lowest the parity tests accept on any backend (CUDA f64: 0.99).
    assert all(CONF_SHARE[fp] <= SHARE[("matching", fp)] for fp in CONF_SHARE)


def test_export_refuses_a_non_empty_folder(golden: Path, capsys) -> None:
    assert main(["conformance", "export", str(golden)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_reference_passes(golden: Path, capsys) -> None:
    rc, out, _ = _check(capsys, str(golden), "--impl", "mslam_ref")
    assert rc == 0, out
    assert set(_verdicts(out).values()) == {"ok"} and len(_verdicts(out)) == len(KERNELS)


@pytest.mark.slow  # compiles every Taichi kernel once per precision
def test_fast_kernels_pass(golden: Path, fast: str, capsys) -> None:
    rc, out, _ = _check(capsys, str(golden), "--impl", "mslam_fast", "--precision", fast)
    assert rc == 0, out
    v = _verdicts(out)
    assert {k for k in v if v[k] == "absent"} == REFERENCE_ONLY
    assert {k for k in v if v[k] == "ok"} == set(KERNELS) - REFERENCE_ONLY


def test_planted_error_fails_and_names_the_kernel(golden: Path, tmp_path: Path, capsys) -> None:
    adapter = tmp_path / "planted.py"
    adapter.write_text(
        "from mslam_ref import sim3\n"
        "def inv(T):\n"
        "    raise RuntimeError('no kernel for this device')\n"
        "KERNELS = {\n"
        "    'sim3.act': lambda T, X: sim3.act(T, X) + 1e-3,\n"
        "    'sim3.exp': sim3.exp,\n"
        "    'sim3.inv': inv,\n"
        "}\n"
    )
    rc, out, _ = _check(capsys, str(golden), "--impl", str(adapter))
    assert rc == 1
    v = _verdicts(out)
    assert v["sim3.act"] == "FAIL" and v["sim3.exp"] == "ok" and v["sim3.inv"] == "FAIL"
    assert "RuntimeError: no kernel for this device" in out
    assert {v[k] for k in KERNELS if k not in ("sim3.act", "sim3.exp", "sim3.inv")} == {"absent"}
    act = next(line for line in out.splitlines() if line.startswith("sim3.act "))
    assert "1.00e-03" in act  # the planted error is the worst error reported


@pytest.mark.parametrize(("stride", "verdict"), [(40, "FAIL"), (200, "ok")])
def test_share_measure_allows_one_percent_of_other_matches(
    golden: Path, tmp_path: Path, capsys, stride: int, verdict: str
) -> None:
    """Every 40th match moved (2.5 % of the pixels) fails; every 200th (0.5 %) passes."""
    adapter = tmp_path / "shifted.py"
    adapter.write_text(
        "from mslam_ref import matching\n"
        "def match(*args):\n"
        "    idx, valid = matching.match(*args)\n"
        "    idx = idx.copy()\n"
        f"    idx[..., ::{stride}] += 1\n"
        "    return idx, valid\n"
        "KERNELS = {'matching.match': match}\n"
    )
    rc, out, _ = _check(capsys, str(golden), "--impl", str(adapter))
    assert _verdicts(out)["matching.match"] == verdict
    assert rc == (1 if verdict == "FAIL" else 0)


def test_example_adapter_over_another_api_passes(golden: Path, capsys) -> None:
    rc, out, _ = _check(capsys, str(golden), "--impl", str(EXAMPLES / "adapter_example.py"))
    assert rc == 0, out
    v = _verdicts(out)
    assert [k for k in KERNELS if v[k] == "ok"] == ["sim3.mul", "sim3.inv", "sim3.act",
                                                    "sim3.to_matrix"]  # fmt: skip


def test_corrupt_case_file_is_one_line_exit_2(golden: Path, tmp_path: Path, capsys) -> None:
    bad = tmp_path / "golden"
    shutil.copytree(golden, bad)
    victim = bad / "tracking.solve" / "calibrated.npz"
    victim.write_bytes(victim.read_bytes()[:300])
    rc, out, err = _check(capsys, str(bad), "--impl", "mslam_ref")
    assert rc == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and "calibrated.npz" in err


@pytest.mark.parametrize(
    ("target", "impl", "needle"),
    [("missing", "mslam_ref", "no such golden-set folder"),
     ("golden", "no_such_package_xyz", "cannot import"),
     ("golden", "missing_adapter.py", "no such adapter file")],
)  # fmt: skip
def test_bad_input_is_one_line_exit_2(golden: Path, tmp_path: Path, capsys, target, impl, needle):
    folder = golden if target == "golden" else tmp_path / target
    rc, out, err = _check(capsys, str(folder), "--impl", str(tmp_path / impl) if
                          impl.endswith(".py") else impl)  # fmt: skip
    assert rc == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and needle in err


def test_adapter_with_an_unknown_kernel_name_is_exit_2(golden: Path, tmp_path: Path, capsys):
    adapter = tmp_path / "typo.py"
    adapter.write_text("KERNELS = {'sim3.actt': print}\n")
    rc, _, err = _check(capsys, str(golden), "--impl", str(adapter))
    assert rc == 2 and "sim3.actt" in err


def test_cpp_reader_reads_a_case_and_checks_sim3_act(golden: Path, tmp_path: Path) -> None:
    gxx = shutil.which("g++")
    if gxx is None:
        pytest.skip("no C++ compiler: g++ is not on PATH (apt-get install -y g++)")
    exe = tmp_path / "read_case"
    subprocess.run([gxx, "-std=c++17", "-O1", "-o", str(exe), str(EXAMPLES / "read_case.cpp")],
                   check=True, capture_output=True)  # fmt: skip
    case = golden / "sim3.act" / "edges.npz"
    listing = subprocess.run([exe, case], check=True, capture_output=True, text=True).stdout
    rows = {line.split()[0]: line for line in listing.splitlines()}
    want = np.load(case)["out.P"]
    assert rows["out.P"].startswith(f"out.P <f8 ({want.shape[0]}, 3)")
    assert float(rows["out.P"].split("first=")[1]) == want.flat[0]
    act = subprocess.run([exe, case, "--act"], capture_output=True, text=True)
    assert act.returncode == 0 and ": ok" in act.stdout
    flags = subprocess.run([exe, golden / "tracking.solve" / "all_invalid.npz"], check=True,
                           capture_output=True, text=True).stdout  # fmt: skip
    assert "out.failed |b1 () first=1" in flags and "out.converged |b1 () first=0" in flags
