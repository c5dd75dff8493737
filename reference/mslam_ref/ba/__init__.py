"""Bundle adjustment — g2o/cuda-bundle-adjustment Levenberg–Marquardt with a Schur complement.

The package namespace is the reference *kernel set* of the BA: ``mslam_ref.ba`` and
``mslam_fast.ba`` both expose ``cameras`` and ``schur`` modules with the same functions, and the
one LM driver (``mslam_ref.ba.lm.optimize``) takes either.

Modules, in reading order: robust, cameras, problem, schur, lm, io, synthetic.
"""

from mslam_ref.ba import cameras, io, lm, problem, robust, schur, synthetic

__all__ = ["cameras", "io", "lm", "problem", "robust", "schur", "synthetic"]
