"""Paper §3.5 (docs/upstream.md §7.3) — edge construction: decode, match both ways, accept.

An edge (i, j) between two keyframes is made like upstream's ``FactorGraph.add_factors``:
the prior decodes the pair both ways, ``pair(i, j)`` and ``pair(j, i)``, matching runs on both
directions in one call per edge, and the per-pixel match quality
``Q_j[n] = sqrt(Q_ii[idx_i2j[n]] · Q_ji[n])`` (and ``Q_i`` likewise) decides the edge's match
fraction ``min(mean(valid_j), mean(valid_i))`` with ``valid = valid_match ∧ Q > Q_conf``. An
edge is rejected when that fraction is below ``min_match_frac`` **unless it is consecutive**
(``i == j - 1``, always accepted).

:class:`EdgeBuilder` holds what every edge needs (the keyframes, the prior, the kernel set,
the matching configuration and ``Q_conf``), so a call names only the pairs and the rule.

Public names, in reading order:
    Edge, cannot_pass, EdgeBuilder
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mslam.kernels import KernelSet
from mslam.priors.base import PairPrediction, Prior
from mslam.system.keyframes import KeyframeStore
from mslam_ref.conventions import BoolArray, FloatArray, IntArray
from mslam_ref.matching import MatchingConfig
from mslam_ref.pointmap import strided_pixels
from mslam_ref.tracking import match_quality

__all__ = ["Edge", "EdgeBuilder", "cannot_pass"]

#: Decodes the frontend already made, by (frame index of i, frame index of j).
KnownPairs = dict[tuple[int, int], PairPrediction]


@dataclass(eq=False)
class Edge:
    """A stored graph edge (i, j) with both directions' matches (upstream ``FactorGraph`` rows).

    Attributes:
        i, j: keyframe indices (upstream ``ii``, ``jj``).
        idx_i2j: (N,) for every pixel of j, the linear index of its match in i.
        idx_j2i: (N,) for every pixel of i, the linear index of its match in j.
        valid_match_j, valid_match_i: (N,) bool validity of those matches.
        Q_j, Q_i: (N,) match quality ``sqrt(Q_ii[idx_i2j] · Q_ji)`` and ``sqrt(Q_jj[idx_j2i] · Q_ij)``.
        match_frac: ``min(mean(valid_j), mean(valid_i))``, the acceptance statistic.
        kind: ``"consecutive"``, ``"retrieval"`` (loop closure) or ``"reloc"``.
    """

    i: int
    j: int
    idx_i2j: IntArray
    idx_j2i: IntArray
    valid_match_j: BoolArray
    valid_match_i: BoolArray
    Q_j: FloatArray
    Q_i: FloatArray
    match_frac: float
    kind: str = "retrieval"


def _flat(a: np.ndarray) -> np.ndarray:
    return a.reshape(-1)


def cannot_pass(p: PairPrediction, Q_conf: float) -> bool:
    """True when no pixel of the decoded pair ``p`` can reach a match quality above ``Q_conf``.

    Every ``Q_j[n] = sqrt(Q_ii[idx_i2j[n]] · Q_ji[n]) <= sqrt(max Q_ii · max Q_ji)``, so when that
    bound is at most ``Q_conf`` the edge's match fraction is 0 whatever the matcher finds (a
    prior that failed on the pair says so with a tiny ``Q_ji``). Deciding this before the
    backward decode and the matching is an early exit with the same outcome.
    """
    return float(np.sqrt(np.max(p.Q_ii) * np.max(p.Q_ji))) <= Q_conf


@dataclass(frozen=True, eq=False)
class EdgeBuilder:
    """Makes candidate edges between keyframes (module docstring).

    Attributes:
        store: the keyframes.
        prior: ``pair(frame_i, frame_j) -> PairPrediction``.
        kernels: the kernel set (``kernels.matching.match``).
        matching_cfg: the matching configuration.
        Q_conf: quality threshold of the validity mask (``local_opt.Q_conf``).
    """

    store: KeyframeStore
    prior: Prior
    kernels: KernelSet
    matching_cfg: MatchingConfig
    Q_conf: float

    def decode(self, ii: list[int], jj: list[int]) -> list[PairPrediction]:
        """The forward decodes ``prior.pair(frame of i, frame of j)``, one per pair."""
        if len(ii) != len(jj):
            raise ValueError(f"ii, jj: lengths differ ({len(ii)} != {len(jj)})")
        return [self.prior.pair(self.store[i].frame, self.store[j].frame) for i, j in zip(ii, jj)]

    def match_pairs(self, ii: list[int], jj: list[int]) -> list[Edge]:
        """Decode and match keyframe pairs both ways; unfiltered edges, ``kind`` at its default.

        Upstream: mast3r_utils.py::mast3r_decode_symmetric_batch, mast3r_match_symmetric;
        global_opt.py::FactorGraph.add_factors (steps 1-4, docs/upstream.md §7.3).
        """
        return self.match(ii, jj, self.decode(ii, jj))

    def match(
        self,
        ii: list[int],
        jj: list[int],
        fwd: list[PairPrediction],
        known: KnownPairs | None = None,
        stride: int = 1,
    ) -> list[Edge]:
        """:meth:`match_pairs` given the forward decodes ``fwd[e] = prior.pair(i, j)``.

        ``stride > 1`` matches only the pixels of the backend's residual grid
        (``mslam_ref.pointmap.strided_pixels``; ``local_opt.pixels_per_edge``): the other
        pixels' points are zeroed, which the matcher skips (their matches are never valid, and
        the solve never reads them), and the match fraction is taken over the grid.

        ``known`` maps (frame index of j, frame index of i) to a decode ``prior.pair`` already
        returned for those frames (the frontend's last tracking pair). For a prior whose
        ``pair`` is a function of the two frames (synthetic, RGB-D, MASt3R) reusing it is
        exact; the two-view prior remembers depths across pairs, so there a skipped decode
        changes what it remembers (still a valid decode of the pair).
        """
        known = known or {}
        edges = []
        for e, (i, j) in enumerate(zip(ii, jj)):
            p = fwd[e]
            frame_i, frame_j = self.store[i].frame, self.store[j].frame
            # The backward decode: X_jj, X_ij in camera j.
            q = known.get((int(frame_j.index), int(frame_i.index))) or self.prior.pair(
                frame_j, frame_i
            )
            edges.append(self._match_one(int(i), int(j), p, q, stride))
        return edges

    def _match_one(self, i: int, j: int, p: PairPrediction, q: PairPrediction, stride: int) -> Edge:
        """One edge from its forward decode ``p`` (camera i) and backward decode ``q`` (j)."""
        H, W = p.X_ii.shape[:2]
        grid = strided_pixels(H, W, stride)
        X_ji = np.stack([p.X_ji, q.X_ji])
        if stride > 1:
            X_ji = np.where(grid[None, ..., None], X_ji, 0.0)
        # One call for both directions: pair 0 gives idx_i2j, pair 1 idx_j2i. Edge by edge
        # (not all edges in one batch): the stacked descriptors of 2E pairs were the run's
        # memory peak at 512x384 (38 MB per pair and copy).
        idx, valid = self.kernels.matching.match(
            np.stack([p.X_ii, q.X_ii]),
            X_ji,
            np.stack([p.D_ii, q.D_ii]),
            np.stack([p.D_ji, q.D_ji]),
            None,
            self.matching_cfg,
        )
        idx = np.asarray(idx, dtype=np.int64)
        valid = np.asarray(valid, dtype=bool).reshape(idx.shape)
        Q_j = match_quality(_flat(p.Q_ii), _flat(p.Q_ji), idx[0])
        Q_i = match_quality(_flat(q.Q_ii), _flat(q.Q_ji), idx[1])
        on = grid.reshape(-1)
        frac_j = float(np.mean((valid[0] & (Q_j > self.Q_conf))[on]))
        frac_i = float(np.mean((valid[1] & (Q_i > self.Q_conf))[on]))
        return Edge(i, j, idx[0], idx[1], valid[0], valid[1], Q_j, Q_i, min(frac_j, frac_i))

    def accepted(
        self,
        ii: list[int],
        jj: list[int],
        min_match_frac: float,
        kind: str = "retrieval",
        known: KnownPairs | None = None,
        stride: int = 1,
        verify: Callable[[Edge], bool] | None = None,
    ) -> tuple[list[Edge], int, int]:
        """The candidate pairs' accepted edges, how many were rejected before matching, and how
        many failed ``verify``.

        Upstream: global_opt.py::FactorGraph.add_factors (docs/upstream.md §7.3).

        Acceptance: an edge is kept when it is consecutive (``i == j - 1``, ``kind =
        "consecutive"``) or its ``match_frac >= min_match_frac`` (``kind`` as given). A
        non-consecutive candidate whose forward decode cannot pass the quality gate
        (:func:`cannot_pass`) is rejected before its backward decode and matching. ``verify``
        (``mslam.system.loop_verify``), when given, must also accept every non-consecutive edge.
        """
        fwd = self.decode(ii, jj)
        doomed = [
            i != j - 1 and min_match_frac > 0 and cannot_pass(p, self.Q_conf)
            for i, j, p in zip(ii, jj, fwd)
        ]
        live = [e for e, d in enumerate(doomed) if not d]
        ii, jj, fwd = [ii[e] for e in live], [jj[e] for e in live], [fwd[e] for e in live]
        keep, unverified = [], 0
        for e in self.match(ii, jj, fwd, known, stride):
            consecutive = e.i == e.j - 1
            e.kind = "consecutive" if consecutive else kind
            if not consecutive and e.match_frac < min_match_frac:
                continue
            if not consecutive and verify is not None and not verify(e):
                unverified += 1
                continue
            keep.append(e)
        return keep, sum(doomed), unverified
