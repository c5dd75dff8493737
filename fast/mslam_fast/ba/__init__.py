"""Taichi twins of the bundle adjuster's hot pieces: ``cameras``, ``schur`` and ``reduced``.

The LM driver is the reference's (``mslam_ref.ba.lm.optimize``); it takes these modules
through its ``kernels`` argument, which the application's kernel set provides
(``mslam.kernels.load_kernels("fast").ba``).
"""

from mslam_fast.ba import cameras, reduced, schur

__all__ = ["cameras", "reduced", "schur"]
