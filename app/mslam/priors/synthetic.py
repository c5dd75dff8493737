"""Synthetic prior — MASt3R-like predictions from ground truth plus a documented noise model.

Frames of a synthetic (or any RGB-D + ground-truth) sequence carry exact depth and poses. This
prior turns them into what the network would return, adding errors of the kinds MASt3R makes,
so that the SLAM system has something honest to correct: it never sees a ground-truth pose
except through these noisy pointmaps.

Noise model for ``pair(i, j)`` (all draws from ``default_rng([seed, 1, i.index, j.index])``,
``mono(i)`` uses ``[seed, 0, i.index]``):

1. **Depth noise** along each pixel's ray, growing with depth:
   ``z' = z + σ(z) n(u, v)``, ``σ(z) = depth_sigma0 + depth_sigma2 z²``, where ``n`` is unit-variance
   Gaussian noise smoothed by a Gaussian of ``noise_blur_px`` (MASt3R's errors are spatially
   smooth) and rescaled to unit variance.
2. **Outliers**: a fraction ``outlier_frac`` of pixels get ``z' = z · exp(±U(0.2, outlier_log))``.
3. **Per-pair scale** (pointmaps are up to an unknown scale per pair): both ``X_ii`` and ``X_ji``
   are multiplied by ``s_pair = exp(pair_log_scale_sigma · n)`` (log-normal).
4. **Per-pair Sim(3) error** of the second view: ``X_ji = s_pair · E_ij · T_ij · X'_jj`` with
   ``T_ij = T_WCi⁻¹ T_WCj`` and ``E_ij = Exp([σ_t n₃, σ_r n₃, σ_s n₁])`` (translation in metres,
   rotation in radians, log-scale).
5. **Confidences** that track the noise: ``C = 1 + conf_max · exp(-σ(z) / conf_sigma)``, divided
   towards 1 by ``edge_factor`` at depth edges, ``1 + U(0, 0.5)`` at outliers, and scaled by
   ``covis_factor`` (towards 1) for pixels of j that camera i does not see.
6. **Descriptors** from image patches (``descriptors.patch_descriptors``) plus per-pair Gaussian
   noise ``desc_noise`` per component, re-normalised; ``Q = 1 + q_gain · tanh(contrast / q_contrast)``,
   multiplied by ``0.3`` at outliers and by ``covis_factor`` for pixels of j unseen from i (so
   they mostly fall below upstream's ``Q_conf = 1.5``).

Public names, in reading order:
    SyntheticPriorConfig, SyntheticPrior
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import cv2
import numpy as np

from mslam.datasets.frame import Frame
from mslam.priors.base import PairPrediction
from mslam.priors.cache import ByteLRU
from mslam.priors.descriptors import DescriptorConfig, descriptor_Q, patch_descriptors
from mslam_ref import sim3
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import backproject, project, scale_intrinsics

__all__ = ["SyntheticPrior", "SyntheticPriorConfig"]


@dataclass(frozen=True)
class SyntheticPriorConfig:
    """Parameters of the synthetic noise model (see the module docstring for each term).

    Attributes:
        seed: base seed (outputs depend only on seed and frame indices).
        depth_sigma0: depth noise floor (m).
        depth_sigma2: depth noise growth (1/m): ``σ(z) = depth_sigma0 + depth_sigma2 z²``.
        noise_blur_px: spatial correlation of the depth noise (Gaussian sigma, pixels; 0 = white).
        outlier_frac: share of pixels that are outliers.
        outlier_log: largest |log| depth factor of an outlier (smallest 0.2).
        pair_log_scale_sigma: std of the log of the per-pair scale.
        rel_trans_sigma: std of the Sim(3) error translation per axis (m).
        rel_rot_sigma: std of the Sim(3) error rotation per axis (rad).
        rel_log_scale_sigma: std of the Sim(3) error log-scale.
        conf_max: confidence ceiling above 1.
        conf_sigma: depth-noise level (m) at which confidence falls by 1/e.
        edge_factor: confidence multiplier (of C - 1) at depth edges.
        edge_threshold: relative depth jump to a 4-neighbour that marks an edge.
        covis_factor: multiplier of C - 1 and of Q for pixels of j unseen from camera i.
        desc_noise: per-component descriptor noise std before re-normalisation.
        q_gain, q_contrast: ``Q = 1 + q_gain tanh(contrast / q_contrast)``.
        desc: patch-descriptor parameters.
    """

    seed: int = 0
    depth_sigma0: float = 0.002
    depth_sigma2: float = 0.003
    noise_blur_px: float = 2.0
    outlier_frac: float = 0.01
    outlier_log: float = 0.7
    pair_log_scale_sigma: float = 0.03
    rel_trans_sigma: float = 0.01
    rel_rot_sigma: float = 0.005
    rel_log_scale_sigma: float = 0.01
    conf_max: float = 20.0
    conf_sigma: float = 0.05
    edge_factor: float = 0.3
    edge_threshold: float = 0.05
    covis_factor: float = 0.2
    desc_noise: float = 0.01
    q_gain: float = 6.0
    q_contrast: float = 0.04
    desc: DescriptorConfig = field(default_factory=DescriptorConfig)

    def __post_init__(self) -> None:
        for name in (
            "depth_sigma0", "depth_sigma2", "noise_blur_px", "outlier_frac", "pair_log_scale_sigma",
            "rel_trans_sigma", "rel_rot_sigma", "rel_log_scale_sigma", "conf_max", "desc_noise",
        ):  # fmt: skip
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.outlier_frac <= 1.0:
            raise ValueError(f"outlier_frac: must be in [0, 1], got {self.outlier_frac}")
        if self.conf_sigma <= 0 or self.q_contrast <= 0 or self.outlier_log < 0.2:
            raise ValueError("conf_sigma, q_contrast must be > 0 and outlier_log >= 0.2")


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], blur: float) -> FloatArray:
    """Unit-variance Gaussian noise with Gaussian spatial correlation of ``blur`` pixels."""
    n = rng.standard_normal(shape)
    if blur <= 0:
        return n
    k = cv2.getGaussianKernel(2 * int(np.ceil(3 * blur)) + 1, blur).ravel()
    smooth = np.asarray(
        cv2.sepFilter2D(n, cv2.CV_64F, k, k, borderType=cv2.BORDER_REFLECT), np.float64
    )
    return smooth / np.sqrt(np.sum(k**2) ** 2)


def _depth_edges(z: FloatArray, thr: float) -> np.ndarray:
    """Pixels whose relative depth jump to a 4-neighbour exceeds ``thr``."""
    lz = np.log(np.maximum(z, 1e-9))
    e = np.zeros(z.shape, dtype=bool)
    dx = np.abs(np.diff(lz, axis=1)) > thr
    dy = np.abs(np.diff(lz, axis=0)) > thr
    e[:, 1:] |= dx
    e[:, :-1] |= dx
    e[1:] |= dy
    e[:-1] |= dy
    return e


class SyntheticPrior:
    """MASt3R stand-in from ground-truth depth and poses plus noise (module docstring).

    Args:
        sequence: provides ``K`` (intrinsics at its native size) and, if it has them,
            ``width``/``height``; frames passed to ``mono``/``pair`` must carry ``depth`` and
            ``T_WC``. Frames of another size get ``K`` rescaled.
        cfg: the noise model.
    """

    #: Pointmaps in metres (made from depth): a keyframe's Sim(3) scale alone is the map's
    #: scale drift (mslam.system.global_opt.Backend.spread_depths).
    metric: ClassVar[bool] = True

    def __init__(self, sequence, cfg: SyntheticPriorConfig = SyntheticPriorConfig()) -> None:
        if sequence.K is None:
            raise ValueError(f"sequence: {sequence.name} has no intrinsics K")
        self.K = np.asarray(sequence.K, dtype=np.float64)
        width, height = getattr(sequence, "width", None), getattr(sequence, "height", None)
        #: ``(W, H)`` at which ``K`` holds, or None when the sequence does not say (then ``K``
        #: is used at every frame size).
        self.size = None if width is None or height is None else (int(width), int(height))
        self.cfg = cfg
        #: Patch descriptors per frame, bounded in bytes.
        self.cache = ByteLRU(cfg.desc.cache_bytes)

    # -- helpers -----------------------------------------------------------------------------
    def _descriptors(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """Patch descriptors of a frame, cached (they depend on the image only)."""
        key = (int(frame.index), frame.rgb.shape, hash(np.ascontiguousarray(frame.rgb).tobytes()))
        return self.cache.get(key, lambda: patch_descriptors(frame.rgb, self.cfg.desc))

    def _K_for(self, frame: Frame) -> FloatArray:
        H, W = frame.shape
        if self.size is None or (W, H) == self.size:
            return self.K
        return scale_intrinsics(self.K, self.size, (W, H))

    @staticmethod
    def _truth(frame: Frame, name: str) -> tuple[FloatArray, FloatArray]:
        """The frame's ``depth`` (H, W) and ``T_WC`` (8,); a ValueError naming ``name`` when
        it lacks either."""
        if frame.depth is None or frame.T_WC is None:
            raise ValueError(f"{name}: the synthetic prior needs frames with depth and T_WC")
        return frame.depth, frame.T_WC

    def sigma(self, z: FloatArray) -> FloatArray:
        """Depth-noise standard deviation ``σ(z) = depth_sigma0 + depth_sigma2 z²`` (metres)."""
        return self.cfg.depth_sigma0 + self.cfg.depth_sigma2 * np.asarray(z) ** 2

    def _noisy_view(
        self, frame: Frame, rng: np.random.Generator
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, np.ndarray]:
        """Noisy pointmap in the frame's own camera, its C, D, Q and the outlier mask."""
        cfg = self.cfg
        z, _ = self._truth(frame, "frame")
        sig = self.sigma(z)
        zn = z + sig * _smooth_noise(rng, z.shape, cfg.noise_blur_px)
        out = rng.random(z.shape) < cfg.outlier_frac
        mag = rng.uniform(0.2, cfg.outlier_log, z.shape) * rng.choice([-1.0, 1.0], z.shape)
        zn = np.where(out, z * np.exp(mag), zn)
        zn = np.maximum(zn, 1e-3)
        X = backproject(zn, self._K_for(frame))
        C = 1.0 + cfg.conf_max * np.exp(-sig / cfg.conf_sigma)
        edges = _depth_edges(z, cfg.edge_threshold)
        C = np.where(edges, 1.0 + (C - 1.0) * cfg.edge_factor, C)
        C = np.where(out, 1.0 + rng.uniform(0.0, 0.5, z.shape), C)
        D, contrast = self._descriptors(frame)
        if cfg.desc_noise > 0:
            D = D + cfg.desc_noise * rng.standard_normal(D.shape)
            D /= np.linalg.norm(D, axis=-1, keepdims=True)
        Q = descriptor_Q(contrast, cfg.q_gain, cfg.q_contrast)
        Q = np.where(out, 0.3 * Q, Q)
        return X, C, D, Q, out

    # -- public ------------------------------------------------------------------------------
    def pair_errors(self, frame_i: Frame, frame_j: Frame) -> tuple[float, FloatArray]:
        """The per-pair scale ``s_pair`` and Sim(3) error ``E_ij`` (8,) that ``pair`` applies."""
        return self._pair_errors(np.random.default_rng(self._pair_seed(frame_i, frame_j)))

    def _pair_seed(self, fi: Frame, fj: Frame) -> list[int]:
        return [int(self.cfg.seed), 1, int(fi.index), int(fj.index)]

    def _pair_errors(self, rng: np.random.Generator) -> tuple[float, FloatArray]:
        cfg = self.cfg
        s_pair = float(np.exp(cfg.pair_log_scale_sigma * rng.standard_normal()))
        xi = np.concatenate(
            [
                cfg.rel_trans_sigma * rng.standard_normal(3),
                cfg.rel_rot_sigma * rng.standard_normal(3),
                [cfg.rel_log_scale_sigma * rng.standard_normal()],
            ]
        )
        return s_pair, sim3.exp(xi)

    def mono(self, frame: Frame) -> tuple[FloatArray, FloatArray]:
        """Noisy ``X_ii (H, W, 3)`` and ``C_ii (H, W)`` of one frame (upstream mono inference).

        Upstream: mast3r_utils.py::mast3r_inference_mono. Noise terms 1, 2, 3 and 5.
        """
        self._truth(frame, "frame")
        rng = np.random.default_rng([int(self.cfg.seed), 0, int(frame.index)])
        s = float(np.exp(self.cfg.pair_log_scale_sigma * rng.standard_normal()))
        X, C, _, _, _ = self._noisy_view(frame, rng)
        return s * X, C

    def pair(self, frame_i: Frame, frame_j: Frame) -> PairPrediction:
        """Noisy asymmetric prediction of (i, j), both pointmaps in camera i.

        Upstream: mast3r_utils.py::mast3r_asymmetric_inference. Paper: §3 (``X^i_i``, ``X^j_i``).

        Returns:
            :class:`PairPrediction` with X (H,W,3), C (H,W), D (H,W,24), Q (H,W) per image.
        """
        _, T_WCi = self._truth(frame_i, "frame_i")
        _, T_WCj = self._truth(frame_j, "frame_j")
        rng = np.random.default_rng(self._pair_seed(frame_i, frame_j))
        s_pair, E = self._pair_errors(rng)
        X_ii, C_ii, D_ii, Q_ii, _ = self._noisy_view(frame_i, rng)
        X_jj, C_jj, D_jj, Q_jj, _ = self._noisy_view(frame_j, rng)
        T_ij = sim3.mul(sim3.inv(T_WCi), T_WCj)
        X_ji = s_pair * sim3.act(sim3.mul(E, T_ij), X_jj)
        unseen = ~self.covisible(frame_i, frame_j)
        f = self.cfg.covis_factor
        C_ji = np.where(unseen, 1.0 + (C_jj - 1.0) * f, C_jj)
        Q_ji = np.where(unseen, Q_jj * f, Q_jj)
        return PairPrediction(s_pair * X_ii, C_ii, D_ii, Q_ii, X_ji, C_ji, D_jj, Q_ji)

    def covisible(self, frame_i: Frame, frame_j: Frame, rel_tol: float = 0.03) -> np.ndarray:
        """(H_j, W_j) mask of the pixels of j whose true surface point camera i sees.

        A pixel of j is covisible when its ground-truth point projects inside image i in front
        of the camera and its depth there agrees with i's depth (nearest pixel) within
        ``rel_tol · z + 0.01`` m.
        """
        z_i, T_WCi = self._truth(frame_i, "frame_i")
        z_j, T_WCj = self._truth(frame_j, "frame_j")
        X_jj = backproject(z_j, self._K_for(frame_j))
        T_ij = sim3.mul(sim3.inv(T_WCi), T_WCj)
        uv, z = project(sim3.act(T_ij, X_jj), self._K_for(frame_i))
        H, W = frame_i.shape
        u, v = np.round(uv[..., 0]), np.round(uv[..., 1])
        ok = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ui = np.clip(u, 0, W - 1).astype(np.int64)
        vi = np.clip(v, 0, H - 1).astype(np.int64)
        zi = z_i[vi, ui]
        return ok & (np.abs(zi - z) <= rel_tol * z + 0.01)
