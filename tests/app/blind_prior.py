"""A prior wrapper that makes some frames blind (a covered lens), shared by the recovery,
map-merging and video-variety tests."""

from __future__ import annotations

import numpy as np


class BlindPrior:
    """Wraps a prior; frames in ``blind`` get the lowest confidence (1) and no descriptor
    quality (a covered lens): pairs that involve them cannot be matched."""

    def __init__(self, prior, blind: range) -> None:
        self._p, self._blind = prior, blind

    def __getattr__(self, name):
        return getattr(self._p, name)

    def mono(self, frame):
        X, C = self._p.mono(frame)
        return X, (np.ones_like(C) if frame.index in self._blind else C)

    def pair(self, frame_i, frame_j):
        p = self._p.pair(frame_i, frame_j)
        if frame_i.index not in self._blind and frame_j.index not in self._blind:
            return p
        one, z = np.ones_like, np.zeros_like
        return type(p)(p.X_ii, one(p.C_ii), p.D_ii, z(p.Q_ii),
                       p.X_ji, one(p.C_ji), p.D_ji, z(p.Q_ji))  # fmt: skip
