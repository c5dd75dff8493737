"""``reconstruction.ply`` keeps the pixels above ``output.C_conf_threshold`` (system.outputs)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mslam.config import load_config
from mslam.system.outputs import C_CONF_THRESHOLD, SCALE_TOLERANCE, reconstruction_points
from mslam_ref import sim3

#: Offset of the stub's tracked pointmap from its map points (an export of it would show).
TRACKED_OFFSET = 100.0


class _Keyframes(list):
    """The two things the export reads from the keyframe store: iteration and pointmaps."""

    def __init__(self, kfs, X, C):
        super().__init__(kfs)
        self.X, self.C = X, C

    def poses(self):
        return np.stack([kf.T_WC for kf in self])

    def pointmaps(self, fusion, K, exported=False):
        # The tracked pointmap (``state.X_canon``) differs from the map's (``X_map``).
        return (self.X if exported else self.X + TRACKED_OFFSET), self.C


def _system(overrides: list[str]) -> SimpleNamespace:
    """One 2x3 keyframe at the identity with confidences 1 (filled depth), 2, 4, 8, 16, 32."""
    H, W = 2, 3
    X = np.arange(H * W * 3, dtype=np.float64).reshape(1, H, W, 3) + 1.0
    C = np.array([[[1.0, 2.0, 4.0], [8.0, 16.0, 32.0]]])
    frame = SimpleNamespace(rgb=np.zeros((H, W, 3), np.uint8))
    kf = SimpleNamespace(shape=(H, W), frame=frame, T_WC=sim3.identity())
    cfg = load_config("base", overrides)
    return SimpleNamespace(cfg=cfg, keyframes=_Keyframes([kf], X, C), K=None, prior=None)


@pytest.mark.parametrize(("overrides", "kept"), [([], 5), (["output.C_conf_threshold=5"], 3)])
def test_export_threshold_is_a_config_key(overrides, kept) -> None:
    xyz, rgb = reconstruction_points(_system(overrides))
    assert len(xyz) == len(rgb) == kept
    assert load_config("base").sections["output"]["C_conf_threshold"] == C_CONF_THRESHOLD
    assert load_config("base").sections["output"]["scale_tolerance"] == SCALE_TOLERANCE


def test_confidence_one_is_never_exported() -> None:
    """Pixels without measured depth get C = 1 from the RGB-D prior: below any threshold >= 1."""
    xyz, _ = reconstruction_points(_system([]), c_thresh=1.0)
    assert len(xyz) == 5 and not np.any(np.all(xyz == [1.0, 2.0, 3.0], axis=1))


def test_the_export_writes_the_map_points_not_the_tracked_pointmap() -> None:
    """``reconstruction.ply`` holds ``Keyframe.X_map`` (fused without filled-in points)."""
    xyz, _ = reconstruction_points(_system([]))
    assert np.all(xyz < TRACKED_OFFSET)
