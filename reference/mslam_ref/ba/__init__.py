"""Bundle adjustment — g2o/cuda-bundle-adjustment Levenberg–Marquardt with a Schur complement.

The hot pieces (``cameras``: residuals and Jacobians; ``schur``: normal blocks, Schur
complement, back-substitution) exist in ``mslam_ref.ba`` and, as Taichi twins, in
``mslam_fast.ba``; the one LM driver (``mslam_ref.ba.lm.optimize``) takes either through its
``kernels`` argument (any object with ``cameras`` and ``schur`` attributes — the application's
kernel set provides one).

Modules, in reading order: robust, cameras, problem, schur, reduced, lm, synthetic.
"""

from mslam_ref.ba import cameras, lm, problem, reduced, robust, schur, synthetic

__all__ = ["cameras", "lm", "problem", "reduced", "robust", "schur", "synthetic"]
