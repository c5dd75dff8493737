"""mslam_fast — Taichi kernels with the same names and signatures as ``mslam_ref``.

Nothing here initialises Taichi at import time. Choose the backend and precision once with
``mslam_fast.init(arch="cpu" | "cuda", default_fp="f64" | "f32")``; without a call, the first
kernel call initialises the CPU backend in float64. Requesting CUDA on a machine without a GPU
raises ``RuntimeError``: it never falls back to the CPU silently.
"""

import os

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")  # no banner on import

from mslam_fast._runtime import current, init

__all__ = ["current", "init"]
__version__ = "0.1.0"
