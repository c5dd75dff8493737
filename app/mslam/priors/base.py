"""Paper §3 / docs/upstream.md §2 — the prior protocol: what a two-view network gives the SLAM system.

MASt3R's asymmetric decoder, run on images (i, j), returns for *both* images a pointmap in
camera i, a confidence, a dense descriptor and a descriptor confidence. Everything downstream
(matching, tracking, fusion, the backend) only needs these arrays, so every source of
pointmaps — the network, a synthetic generator, an RGB-D camera — implements one protocol:

* ``mono(frame) -> (X_ii (H, W, 3), C_ii (H, W))`` — upstream ``mast3r_inference_mono``;
* ``pair(frame_i, frame_j) -> PairPrediction`` — upstream ``mast3r_asymmetric_inference``.

Invariants (docs/upstream.md §2.1 output activations): ``C >= 1``, ``‖D‖ = 1`` per pixel with F = 24,
``Q > 0``, all finite. ``C = NO_INFO_C`` (exactly 1, which MASt3R's ``1 + exp(·)`` never reaches)
marks a pixel whose point carries no measurement: depth filled in from a neighbour (RGB-D
pixels without depth, two-view pixels that failed triangulation) or a degenerate pair's plane.
The map's fusion keeps such points out of the exported positions and the export never writes
them (``mslam.system.tracker.without_filler``, ``output.C_conf_threshold`` > 1).

A prior whose pointmaps are in metres (made from depth) says so with a class attribute
``metric = True``; one without the attribute counts as normalised, as MASt3R's are.
:func:`is_metric` is the one place that reads it: for the spread watch (what can drift,
``mslam.system.global_opt.Backend.spread_depths``), and, kept in the run's metadata and
``summary.json`` as ``prior_metric``, for the aligned-scale check (``mslam.system.health``),
the console line and the trajectory plot's units.

Public names, in reading order:
    DESC_DIM, NO_INFO_C, PairPrediction, Prior, is_metric, check_prediction
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Protocol, runtime_checkable

import numpy as np

from mslam.datasets.frame import Frame
from mslam_ref.conventions import FloatArray

__all__ = ["DESC_DIM", "NO_INFO_C", "PairPrediction", "Prior", "check_prediction", "is_metric"]

#: MASt3R's descriptor dimension F (``output_mode='pts3d+desc24'``).
DESC_DIM = 24

#: Confidence of a point without a measurement (filled depth, a degenerate pair's plane).
NO_INFO_C = 1.0


@dataclass(frozen=True, eq=False)
class PairPrediction:
    """Outputs of one asymmetric two-view inference (i, j), all expressed in camera i.

    Upstream: mast3r_utils.py::mast3r_asymmetric_inference (``res11``, ``res21``).

    Attributes:
        X_ii: (H_i, W_i, 3) pointmap of image i in camera i.
        C_ii: (H_i, W_i) confidence, >= 1.
        D_ii: (H_i, W_i, F) unit descriptors of image i.
        Q_ii: (H_i, W_i) descriptor confidence, > 0.
        X_ji: (H_j, W_j, 3) pointmap of image j in camera i.
        C_ji, D_ji, Q_ji: as above for image j.
    """

    X_ii: FloatArray
    C_ii: FloatArray
    D_ii: FloatArray
    Q_ii: FloatArray
    X_ji: FloatArray
    C_ji: FloatArray
    D_ji: FloatArray
    Q_ji: FloatArray

    def __post_init__(self) -> None:
        for f in fields(self):
            dtype = np.asarray(getattr(self, f.name)).dtype
            if dtype == np.bool_ or not np.issubdtype(dtype, np.number):
                raise ValueError(f"{f.name}: expected a numeric array, got dtype {dtype}")
        for side in ("ii", "ji"):
            X = getattr(self, f"X_{side}")
            H, W = X.shape[:2]
            expect = {"X": (H, W, 3), "C": (H, W), "Q": (H, W)}
            for key, shape in expect.items():
                arr = getattr(self, f"{key}_{side}")
                if arr.shape != shape:
                    raise ValueError(f"{key}_{side}: expected shape {shape}, got {arr.shape}")
            D = getattr(self, f"D_{side}")
            if D.ndim != 3 or D.shape[:2] != (H, W) or D.shape[2] == 0:
                raise ValueError(f"D_{side}: expected shape ({H}, {W}, F), F >= 1, got {D.shape}")


@runtime_checkable
class Prior(Protocol):
    """Anything that predicts pointmaps like MASt3R (see the module docstring)."""

    def mono(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """``X_ii (H, W, 3), C_ii (H, W)`` of one image."""
        ...

    def pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        """Both pointmaps, confidences and descriptors of (i, j) in camera i."""
        ...


def is_metric(prior: object) -> bool:
    """Whether ``prior``'s pointmaps are in metres: its class attribute ``metric``, False when
    absent (a wrapper such as ``mslam.system.worker.SharedPrior`` passes it through)."""
    return bool(getattr(prior, "metric", False))


def check_prediction(pred: PairPrediction, desc_dim: int = DESC_DIM, atol: float = 1e-5) -> None:
    """Raise ``ValueError`` unless ``pred`` meets the protocol invariants.

    Checks: finite arrays, ``C >= 1``, ``Q > 0``, ``|‖D‖ - 1| <= atol``, ``D.shape[-1] == F``
    (``atol`` admits float32 descriptors, as networks and the patch stand-in give).
    """
    for f in fields(pred):
        arr = getattr(pred, f.name)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{f.name}: contains non-finite values")
    for side in ("ii", "ji"):
        C, D, Q = (getattr(pred, f"{k}_{side}") for k in "CDQ")
        if np.any(C < 1.0):
            raise ValueError(f"C_{side}: confidences must be >= 1 (min {C.min()})")
        if np.any(Q <= 0.0):
            raise ValueError(f"Q_{side}: descriptor confidences must be > 0 (min {Q.min()})")
        if D.shape[-1] != desc_dim:
            raise ValueError(f"D_{side}: expected F = {desc_dim}, got {D.shape[-1]}")
        err = np.abs(np.linalg.norm(D, axis=-1) - 1.0).max(initial=0.0)
        if err > atol:
            raise ValueError(f"D_{side}: descriptors must have unit norm (max error {err:.2e})")
