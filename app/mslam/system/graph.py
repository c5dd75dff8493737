"""Paper §3.5 (docs/upstream.md §7.3–7.4) — the factor graph: stored edges, two-way blocks.

The graph stores the accepted edges between keyframes (made by
:class:`~mslam.system.edges.EdgeBuilder`, docs/upstream.md §7.3) and counts the candidates it
was offered. Each stored edge gives two directed residual blocks for the backend
(:meth:`FactorGraph.two_way_blocks`). Like upstream, the graph is never pruned.

Public names, in reading order:
    FactorGraph
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from mslam.system.edges import Edge, EdgeBuilder, KnownPairs
from mslam_ref import backend
from mslam_ref.conventions import IntArray

__all__ = ["FactorGraph"]


@dataclass
class FactorGraph:
    """Stored edges of the keyframe graph (upstream global_opt.py::FactorGraph).

    The graph is never pruned; ``window_size`` is unused upstream too.
    """

    edges: list[Edge] = field(default_factory=list)
    candidates_tested: int = 0
    candidates_rejected_early: int = 0
    candidates_unverified: int = 0

    def __len__(self) -> int:
        return len(self.edges)

    def add_factors(
        self,
        builder: EdgeBuilder,
        ii: list[int],
        jj: list[int],
        min_match_frac: float,
        kind: str = "retrieval",
        known: KnownPairs | None = None,
        stride: int = 1,
        verify: Callable[[Edge], bool] | None = None,
    ) -> bool:
        """Make the candidate edges (ii[e], jj[e]) and store the accepted ones; True if any.

        Upstream: global_opt.py::FactorGraph.add_factors (docs/upstream.md §7.3); the rule is
        :meth:`~mslam.system.edges.EdgeBuilder.accepted` (``known``: decodes already made;
        ``stride``: the residual grid to match; ``verify``: the loop-closure check).
        """
        added, early, unverified = builder.accepted(
            ii, jj, min_match_frac, kind, known, stride, verify
        )
        self.candidates_tested += len(ii)
        self.candidates_rejected_early += early
        self.candidates_unverified += unverified
        self.edges.extend(added)
        return bool(added)

    def remove_keyframe(self, k: int) -> None:
        """Drop every edge touching keyframe ``k`` (used when a relocalisation is undone)."""
        self.edges = [e for e in self.edges if k not in (e.i, e.j)]

    def count(self, kind: str) -> int:
        """Number of stored edges of one kind."""
        return sum(e.kind == kind for e in self.edges)

    def two_way_blocks(self, pixels: IntArray | None = None, first: int = 0) -> SimpleNamespace:
        """Directed residual blocks of all edges (upstream ``prep_two_way_edges``, docs/upstream.md §7.4)
        between keyframes ``first`` and later (the current map, ``mslam.system.recovery``).

        Edge (i, j) gives block (i ← j) with ``idx_i2j, valid_match_j, Q_j`` (residuals over
        the pixels of j, reference pixel in i) and block (j ← i) with ``idx_j2i,
        valid_match_i, Q_i``.

        Args:
            pixels: (N,) the pixels (of each block's j) to keep; None keeps all H·W.

        Returns:
            namespace with ii (D,), jj (D,) int64, idx (D, N) int64, valid (D, N) bool,
            Q (D, N) float64, D = 2E.
        """
        edges = [e for e in self.edges if min(e.i, e.j) >= first]
        if not edges:
            z = np.zeros(0, dtype=np.int64)
            empty = (np.zeros((0, 0), np.int64), np.zeros((0, 0), bool), np.zeros((0, 0)))
            return SimpleNamespace(ii=z, jj=z, idx=empty[0], valid=empty[1], Q=empty[2])
        cols = slice(None) if pixels is None else pixels
        stack = lambda name: np.stack([getattr(e, name)[cols] for e in edges])
        ii, jj, idx, valid, Q = backend.directed_blocks(
            [e.i for e in edges],
            [e.j for e in edges],
            stack("idx_i2j"),
            stack("idx_j2i"),
            stack("valid_match_j"),
            stack("valid_match_i"),
            stack("Q_j"),
            stack("Q_i"),
        )
        return SimpleNamespace(ii=ii, jj=jj, idx=idx, valid=valid, Q=Q)
