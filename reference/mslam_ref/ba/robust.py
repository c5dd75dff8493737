"""Bundle adjustment — robust kernels as g2o applies them (first-order IRLS).

For an edge with residual ``r`` and scalar information ``omega`` the squared error is
``s = omega |r|^2``. The cost contributed is ``rho(s)``; the linear system uses the effective
information ``omega rho'(s)`` in both ``H`` and ``b`` (g2o ``robustInformation`` without the
``rho''`` term, the same as cuda-bundle-adjustment).

    Huber(delta):  rho(s) = s                              s <= delta^2
                          = 2 delta sqrt(s) - delta^2      otherwise
                   rho'(s) = 1 or delta / sqrt(s)
    Tukey(delta):  rho(s) = delta^2/3 (1 - (1 - s/delta^2)^3)   s <= delta^2
                          = delta^2/3                           otherwise
                   rho'(s) = (1 - s/delta^2)^2 or 0

Public names, in reading order: RobustKernel, rho_and_weight.

Upstream: g2o core/robust_kernel_impl.cpp (RobustKernelHuber::robustify,
RobustKernelTukey::robustify); cuda-bundle-adjustment src/cuda_block_solver.cu (the robust
chi2 and weight device functions).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mslam_ref.conventions import FloatArray

__all__ = ["KINDS", "RobustKernel", "rho_and_weight"]

#: Supported kernel names.
KINDS = ("none", "huber", "tukey")


@dataclasses.dataclass(frozen=True)
class RobustKernel:
    """A robust kernel: ``kind`` in {"none", "huber", "tukey"} and its parameter ``delta`` > 0.

    ORB-SLAM2 (and cuda-bundle-adjustment's comparison sample) use Huber with
    ``delta = sqrt(5.991)`` for mono and ``sqrt(7.815)`` for stereo edges.
    """

    kind: str = "none"
    delta: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {self.kind!r}")
        if not (np.isfinite(self.delta) and self.delta > 0.0):
            raise ValueError(f"delta: must be finite and positive, got {self.delta!r}")


def rho_and_weight(s: FloatArray, kernel: RobustKernel) -> tuple[FloatArray, FloatArray]:
    """Robust cost ``rho(s)`` and IRLS weight ``rho'(s)`` of squared errors ``s >= 0``.

    Upstream: g2o robust_kernel_impl.cpp::RobustKernelHuber::robustify / RobustKernelTukey.

    Args:
        s: (O,) squared errors ``omega |r|^2``.
        kernel: the kernel.

    Returns:
        rho (O,), weight (O,) (both float64; weight in [0, 1]).
    """
    s = np.asarray(s, dtype=np.float64)
    if kernel.kind == "none":
        return s.copy(), np.ones_like(s)
    d2 = kernel.delta**2
    inside = s <= d2
    if kernel.kind == "huber":
        sq = np.sqrt(np.where(inside, 1.0, s))
        rho = np.where(inside, s, 2.0 * kernel.delta * sq - d2)
        w = np.where(inside, 1.0, kernel.delta / sq)
        return rho, w
    a = np.where(inside, 1.0 - s / d2, 0.0)
    rho = np.where(inside, d2 / 3.0 * (1.0 - a**3), d2 / 3.0)
    return rho, a * a
