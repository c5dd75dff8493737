"""The device a run computes on: ``cpu`` or ``cuda``, for the Taichi kernels and the network.

One switch (``mslam run --device``, ``mslam ba --device``, the Python API's ``device=``) sets
both the Taichi arch of the fast kernels and the torch device of the MASt3R prior. There is no
silent fallback: asking for CUDA where no NVIDIA driver can be loaded is a ``ValueError`` (the
command line prints it as one line and exits with 2) before any work, and Taichi is then never
initialised for CUDA (its own failure prints C++ log lines on stderr).

Public names, in reading order:
    DEVICES, cuda_driver_present, use_device
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["DEVICES", "cuda_driver_present", "use_device"]

#: Accepted ``--device`` values.
DEVICES = ("cpu", "cuda")


def cuda_driver_present() -> bool:
    """Whether the NVIDIA driver library (``libcuda``) can be loaded in this process."""
    for name in ("libcuda.so.1", "libcuda.so", ctypes.util.find_library("cuda")):
        if not name:
            continue
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


def use_device(device: str, kernels: str, precision: str = "f64") -> None:
    """Initialise the fast kernels on ``device`` (nothing to do for the NumPy reference on CPU).

    Args:
        device: ``"cpu"`` or ``"cuda"``.
        kernels: the kernel set, ``"ref"`` or ``"fast"``.
        precision: ``"f64"`` or ``"f32"`` (fast kernels).

    Raises:
        ValueError: an unknown device, CUDA without a loadable driver or usable GPU, or CUDA
            with the reference kernels (NumPy runs on the CPU only).
    """
    if device not in DEVICES:
        raise ValueError(f"--device: unknown device {device!r}; choose one of {', '.join(DEVICES)}")
    if device == "cuda" and kernels != "fast":
        raise ValueError("--device cuda: the ref kernels are NumPy (CPU only); use --kernels fast")
    if device == "cuda" and not cuda_driver_present():
        raise ValueError(
            "--device cuda: no NVIDIA driver (libcuda) on this machine; use --device cpu"
        )
    if kernels != "fast":
        return
    import mslam_fast

    try:
        mslam_fast.init(device, precision)
    except RuntimeError as exc:
        raise ValueError(f"--device {device}: {exc}") from None
