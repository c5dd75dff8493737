"""mslam_ref — the readable NumPy/SciPy reference of MASt3R-SLAM and an LM/Schur bundle adjuster.

Every module implements one concept of the paper (arXiv:2412.12392v2) in float64 NumPy and is the
oracle that the Taichi kernels of ``mslam_fast`` are tested against. This package never imports
taichi.
"""

__version__ = "0.1.0"
