"""The one table of parity tolerances, fast (Taichi, CPU) against reference (NumPy, float64).

Each row: (module, precision) -> rtol/atol for ``np.testing.assert_allclose`` and, in the comment,
the worst case measured on the 2-core CI machine. Kernel-specific parity criteria that are not
allclose-style (integer matches, validity masks) are listed as shares in ``SHARE``.
"""

from __future__ import annotations

TOL: dict[tuple[str, str], dict[str, float]] = {
    # Sim(3)/SO(3) maps on O(1) inputs; worst f64 case ~1e-13, f32 ~3e-6.
    ("sim3", "f64"): {"rtol": 1e-10, "atol": 1e-10},
    ("sim3", "f32"): {"rtol": 2e-4, "atol": 2e-4},
    ("so3", "f64"): {"rtol": 1e-10, "atol": 1e-10},
    ("so3", "f32"): {"rtol": 2e-4, "atol": 2e-4},
    # Tracking 7x7 H and g, backend 14x14 blocks: sums over ~2e5 pixels accumulated in f64.
    ("tracking", "f64"): {"rtol": 1e-9, "atol": 1e-9},
    ("tracking", "f32"): {"rtol": 1e-2, "atol": 1e-3},
    ("backend", "f64"): {"rtol": 1e-9, "atol": 1e-9},
    ("backend", "f32"): {"rtol": 1e-2, "atol": 1e-3},
    ("fusion", "f64"): {"rtol": 1e-12, "atol": 1e-12},
    ("fusion", "f32"): {"rtol": 1e-5, "atol": 1e-5},
    # Bundle adjustment residuals, Jacobians and Schur products.
    ("ba", "f64"): {"rtol": 1e-9, "atol": 1e-9},
    ("ba", "f32"): {"rtol": 1e-3, "atol": 1e-3},
}

#: Minimum share of pixels on which fast and reference agree exactly (integer outputs).
SHARE: dict[tuple[str, str], float] = {
    ("matching", "f64"): 0.999,
    ("matching", "f32"): 0.99,
}


def tol(module: str, fp: str) -> dict[str, float]:
    """``rtol``/``atol`` keyword arguments for ``np.testing.assert_allclose``."""
    return TOL[(module, fp)]
