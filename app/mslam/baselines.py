"""A classical peer for the RGB-D runs: frame-to-frame dense RGB-D odometry (OpenCV).

MASt3R-SLAM's tables compare against learned and classical SLAM systems that we cannot run
here. As an honest, always-available classical reference on RGB-D input, this module chains
OpenCV's dense RGB-D odometry (``cv2.Odometry`` with ``OdometryType_RGB_DEPTH``, the
photometric + ICP method of Steinbrücker et al. 2011 / Whelan et al.) from each frame to the
next — no keyframes, no loop closure, no global optimisation — and scores it with the same
ATE as the SLAM run.

``cv2.Odometry.compute(src, dst)`` returns ``Rt`` with ``Rt · X_src = X_dst``, i.e.
``T_{C_dst C_src}``; so ``T_WC[k] = T_WC[k-1] · Rt⁻¹``. A failed step (OpenCV reports failure,
e.g. beyond its motion limits) keeps the previous pose (constant position) and is counted.

Public names, in reading order:
    OdometryResult, rgbd_odometry, rgbd_odometry_ate
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mslam_ref import sim3
from mslam_ref.conventions import FloatArray

__all__ = ["OdometryResult", "rgbd_odometry", "rgbd_odometry_ate"]


@dataclass(frozen=True)
class OdometryResult:
    """Poses of the odometry chain.

    Attributes:
        timestamps: (M,) stamps of the frames read. T_WC: (M, 8) Sim(3) poses (s = 1), the
            first frame at identity. failures: steps OpenCV rejected. seconds: wall time.
    """

    timestamps: FloatArray
    T_WC: FloatArray
    failures: int
    seconds: float


def _settings(K: FloatArray, max_translation: float, max_rotation_deg: float) -> Any:
    s = cv2.OdometrySettings()
    s.setCameraMatrix(np.asarray(K, dtype=np.float32))
    s.setMaxTranslation(float(max_translation))
    s.setMaxRotation(float(max_rotation_deg))
    s.setMinDepth(0.05)
    s.setMaxDepth(10.0)
    return s


def rgbd_odometry(
    sequence: Any, max_translation: float = 0.5, max_rotation_deg: float = 30.0
) -> OdometryResult:
    """Chain ``cv2.Odometry`` (RGB + depth) over consecutive frames of ``sequence``.

    Args:
        sequence: frames with ``rgb`` and metric ``depth``; ``sequence.K`` (3, 3) intrinsics.
        max_translation: OpenCV's per-step translation limit (m).
        max_rotation_deg: OpenCV's per-step rotation limit (degrees).

    Returns:
        :class:`OdometryResult`. Unreadable frames are skipped.

    Raises:
        ValueError: no intrinsics or no depth.
    """
    if sequence.K is None:
        raise ValueError("sequence: RGB-D odometry needs intrinsics K")
    od = cv2.Odometry(
        cv2.OdometryType_RGB_DEPTH,
        _settings(sequence.K, max_translation, max_rotation_deg),
        cv2.OdometryAlgoType_COMMON,
    )
    t0 = time.perf_counter()
    stamps, poses, failures = [], [], 0
    prev = None
    T = sim3.identity()
    for i in range(len(sequence)):
        try:
            f = sequence[i]
        except (OSError, ValueError, cv2.error):
            continue
        if f.depth is None:
            raise ValueError(f"frame {i}: RGB-D odometry needs depth")
        grey = cv2.cvtColor(np.ascontiguousarray(f.rgb), cv2.COLOR_RGB2GRAY)
        cur = cv2.OdometryFrame(f.depth.astype(np.float32), grey)
        od.prepareFrame(cur)
        if prev is not None:
            ok, Rt = od.compute(prev, cur)
            if ok and np.all(np.isfinite(Rt)):
                T = sim3.mul(T, sim3.from_matrix(np.asarray(np.linalg.inv(Rt), np.float64)))
            else:
                failures += 1
        prev = cur
        stamps.append(float(f.timestamp))
        poses.append(T.copy())
    return OdometryResult(
        np.asarray(stamps), np.asarray(poses).reshape(-1, 8), failures, time.perf_counter() - t0
    )


def rgbd_odometry_ate(sequence: Any) -> dict[str, Any]:
    """Run :func:`rgbd_odometry` and score it (ATE, Sim(3)) against the sequence's ground truth.

    Returns:
        JSON-ready dict: ``method``, ``frames``, ``failures``, ``seconds``, and ``ate_rmse``,
        ``ate`` (evaluate.AteResult.to_dict) when ground truth exists; ``error`` if OpenCV
        failed outright (the baseline is optional); ``_result`` holds the
        :class:`OdometryResult` (underscore keys are not written to summary.json).
    """
    from mslam import evaluate

    out: dict[str, Any] = {"method": "OpenCV RGB-D odometry (frame to frame)"}
    try:
        res = rgbd_odometry(sequence)
    except (cv2.error, ValueError) as exc:
        out["error"] = str(exc).strip().splitlines()[-1]
        return out
    out.update(frames=len(res.timestamps), failures=res.failures, seconds=res.seconds)
    out["_result"] = res  # the trajectory itself (baseline_odometry.txt, the plot); not JSON
    truth = sequence.ground_truth()
    if truth is not None and len(res.timestamps) >= 3:
        a = evaluate.ate(res.timestamps, res.T_WC, truth[1], truth[2], "sim3")
        out["ate"] = a.to_dict()
        out["ate_rmse"] = a.rmse
    return out
