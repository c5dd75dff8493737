"""Taichi kernel set of the bundle adjuster: ``cameras`` and ``schur`` twins, and ``lm``.

Pass this package as ``kernels`` to ``mslam_ref.ba.lm.optimize`` (or call
``mslam_fast.ba.lm.optimize``, which does so).
"""

from mslam_fast.ba import cameras, lm, schur

__all__ = ["cameras", "lm", "schur"]
