"""mslam_ref — the oracle: a readable NumPy/SciPy reference of MASt3R-SLAM and an LM/Schur BA.

Every module implements one concept of the paper (Murai, Dexheimer, Davison, "MASt3R-SLAM",
CVPR 2025, arXiv:2412.12392v2) in float64 NumPy, in the paper's order: conventions, so3, sim3,
se3, pointmap, calib, robust, image_ops, matching_inputs, matching, tracking, fusion, backend,
retrieval, gauss_newton, synthetic, and ba/ (the bundle adjuster). It is the oracle that the
Taichi kernels of ``mslam_fast`` are tested against.

This package depends on numpy, scipy and the standard library only: it never imports taichi,
OpenCV, YAML, tqdm, matplotlib or torch, nor ``mslam_fast`` or the ``mslam`` application
(``tests/test_layers.py`` holds this).
"""

__version__ = "0.1.0"
