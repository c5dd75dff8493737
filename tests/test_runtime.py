"""``mslam_fast.init``: lazy, idempotent, validated, never a silent CPU fallback for CUDA."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tolerances import tol

import mslam_fast
import mslam_fast.sim3 as F
from mslam_fast import _runtime
from mslam_ref import sim3 as R

ROOT = Path(__file__).resolve().parents[1]
HAS_NVIDIA = shutil.which("nvidia-smi") is not None


@pytest.fixture
def restore_cpu():
    """Put the CPU/f64 runtime back after a test that switches or breaks it."""
    yield
    mslam_fast.init("cpu", "f64")


def test_import_does_not_initialise_taichi() -> None:
    code = (
        "import taichi as ti, mslam_fast, mslam_fast.sim3, mslam_fast.so3\n"
        "from taichi.lang import impl\n"
        "assert mslam_fast.current() is None\n"
        "assert impl.get_runtime().prog is None, 'ti.init ran at import'\n"
        "import numpy as np\n"
        "mslam_fast.sim3.act(np.array([0, 0, 0, 0, 0, 0, 1, 1.0]), np.ones(3))\n"
        "assert mslam_fast.current() == mslam_fast._runtime.Runtime('cpu', 'f64')\n"
    )
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT / "reference"), str(ROOT / "fast")]),
    }
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]


def test_init_is_idempotent(restore_cpu: None) -> None:
    a = mslam_fast.init("cpu", "f64")
    b = mslam_fast.init("cpu", "f64")
    assert a == b == mslam_fast.current()
    assert a.dtype is np.float64


@pytest.mark.parametrize("spelling", ["f32", "float32", np.float32, "F32"])
def test_init_accepts_f32_spellings(restore_cpu: None, spelling: object) -> None:
    rt = mslam_fast.init("cpu", spelling)
    assert rt.fp == "f32" and rt.dtype is np.float32
    assert F.act(R.identity(), np.ones(3)).dtype == np.float32


def test_init_accepts_taichi_types(restore_cpu: None) -> None:
    import taichi as ti

    assert mslam_fast.init("cpu", ti.f32).fp == "f32"
    assert mslam_fast.init("cpu", ti.f64).fp == "f64"


def test_switching_precision_recompiles_kernels(restore_cpu: None) -> None:
    T, X = R.exp(np.arange(7.0) * 0.1), np.ones(3)
    for fp in ("f64", "f32", "f64"):
        mslam_fast.init("cpu", fp)
        out = F.act(T, X)
        np.testing.assert_allclose(out, R.act(T, X), **tol("sim3", fp))


@pytest.mark.parametrize("arch", ["gpu", "CPU", "metal", "", None])
def test_bad_arch_raises(arch: object) -> None:
    with pytest.raises(ValueError, match=r"^arch: "):
        mslam_fast.init(arch, "f64")  # type: ignore[arg-type]


@pytest.mark.parametrize("fp", ["f16", "double", "fp64", np.float16, 64])
def test_bad_precision_raises(fp: object) -> None:
    with pytest.raises(ValueError, match=r"^default_fp: "):
        mslam_fast.init("cpu", fp)


@pytest.mark.skipif(HAS_NVIDIA, reason="a GPU driver exists here")
def test_cuda_without_gpu_raises_and_does_not_fall_back(restore_cpu: None) -> None:
    mslam_fast.init("cpu", "f32")
    with pytest.raises(RuntimeError, match="cuda"):
        mslam_fast.init("cuda", "f64")
    # Not a silent CPU runtime in the asked precision: the earlier choice (f32) stays.
    assert mslam_fast.current() == _runtime.Runtime("cpu", "f32")
    T = R.exp(np.arange(7.0) * 0.1)
    got = F.act(T, np.ones(3))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, R.act(T, np.ones(3)), **tol("sim3", "f32"))


@pytest.mark.gpu
@pytest.mark.parametrize("fp", ["f64", "f32"])
def test_sim3_parity_on_cuda(restore_cpu: None, fp: str) -> None:
    if not HAS_NVIDIA:
        pytest.skip("no GPU here")
    mslam_fast.init("cuda", fp)
    rng = np.random.default_rng(6)
    T = R.exp(rng.normal(size=(4096, 7)))
    B = R.exp(rng.normal(size=(4096, 7)))
    X = rng.normal(size=(4096, 3)) * 5.0
    xi = rng.normal(size=(4096, 7))
    t = tol("sim3", fp)
    np.testing.assert_allclose(F.exp(xi), R.exp(xi), **t)
    np.testing.assert_allclose(F.log(T), R.log(T), **t)
    np.testing.assert_allclose(F.mul(T, B), R.mul(T, B), **t)
    np.testing.assert_allclose(F.inv(T), R.inv(T), **t)
    np.testing.assert_allclose(F.act(T, X), R.act(T, X), **t)
    for got, want in zip(F.act_and_jacobian(T, X), R.act_and_jacobian(T, X), strict=True):
        np.testing.assert_allclose(got, want, **t)
    np.testing.assert_allclose(F.adjoint(T), R.adjoint(T), **t)
    np.testing.assert_allclose(F.adjoint_inv_apply(T, xi), R.adjoint_inv_apply(T, xi), **t)
    np.testing.assert_allclose(F.retract(T, xi), R.retract(T, xi), **t)
    np.testing.assert_allclose(F.to_matrix(T), R.to_matrix(T), **t)
