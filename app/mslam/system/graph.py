"""Paper §3.5 (docs/upstream.md §7.3–7.4) — the factor graph: stored edges, two-way blocks.

The graph stores the accepted edges between keyframes (made by
:class:`~mslam.system.edges.EdgeBuilder`, docs/upstream.md §7.3) and counts the candidates it
was offered. Each stored edge gives two directed residual blocks for the backend
(:meth:`FactorGraph.two_way_blocks`). Like upstream, the graph is never pruned.

A solve need not move every keyframe: :meth:`FactorGraph.window` picks the keyframes a
windowed solve moves (the ``local_opt.window_size`` most recent, and the newest keyframe's
loop-closure partners) and the ones it holds fixed (every other keyframe that shares an edge
with a moved one), so a solve's cost stays bounded as the map grows; upstream reads
``window_size`` but always solves over the whole graph (the default, 1e6, does too).

Public names, in reading order:
    SolveWindow, FactorGraph
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from mslam.system.edges import Edge, EdgeBuilder, KnownPairs
from mslam_ref import backend
from mslam_ref.conventions import IntArray

__all__ = ["FactorGraph", "SolveWindow"]


@dataclass(frozen=True)
class SolveWindow:
    """The keyframes of one solve: ``keyframes[:pin]`` held fixed, the rest moved.

    Attributes:
        keyframes: (K',) keyframe indices of the solve, the fixed ones first, each part sorted.
        pin: how many leading ``keyframes`` stay fixed (``BackendConfig.pin``), at least 1.
        windowed: False when the solve covers every keyframe (``keyframes = arange(K)``,
            ``pin = 1``: the whole-graph solve, bit for bit).
    """

    keyframes: IntArray
    pin: int
    windowed: bool


@dataclass
class FactorGraph:
    """Stored edges of the keyframe graph (upstream global_opt.py::FactorGraph).

    The graph is never pruned; :meth:`window` picks the keyframes one solve moves.
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

    def window(self, n_keyframes: int, size: float, first: int = 0) -> SolveWindow:
        """The keyframes a solve over keyframes ``first..n_keyframes-1`` moves and holds fixed.

        Moved: the ``size`` most recent keyframes and the keyframes that share an edge with the
        newest one (its loop closures, so a revisit also corrects the old keyframes it meets).
        Held fixed: every other keyframe of the map sharing an edge with a moved one; they
        anchor the moved keyframes (and fix the gauge). Edges between two fixed keyframes do
        not enter the solve. When the recent keyframes cover the whole map the window is the
        whole graph (``keyframes = arange(n_keyframes)``, ``pin = 1``).

        Args:
            n_keyframes: K, the number of keyframes (all maps).
            size: ``local_opt.window_size``, the recent keyframes moved (>= 1).
            first: the current map's first keyframe (``mslam.system.recovery``).

        Returns:
            a :class:`SolveWindow`.
        """
        n_recent = int(min(size, n_keyframes))
        start = n_keyframes - max(1, n_recent)
        if start <= first:
            return SolveWindow(np.arange(n_keyframes, dtype=np.int64), 1, False)
        edges = [e for e in self.edges if min(e.i, e.j) >= first]
        newest = n_keyframes - 1
        moved = set(range(start, n_keyframes))
        moved |= {e.i + e.j - newest for e in edges if newest in (e.i, e.j)}
        fixed = {e.i if e.j in moved else e.j for e in edges if (e.i in moved) != (e.j in moved)}
        if not fixed:  # nothing anchors the window: its oldest keyframe holds the gauge
            ordered = sorted(moved)
            return SolveWindow(np.array(ordered, dtype=np.int64), 1, True)
        ordered = sorted(fixed) + sorted(moved)
        return SolveWindow(np.array(ordered, dtype=np.int64), len(fixed), True)

    def two_way_blocks(
        self, pixels: IntArray | None = None, first: int = 0, window: SolveWindow | None = None
    ) -> SimpleNamespace:
        """Directed residual blocks of all edges (upstream ``prep_two_way_edges``, docs/upstream.md §7.4)
        between keyframes ``first`` and later (the current map, ``mslam.system.recovery``).

        Edge (i, j) gives block (i ← j) with ``idx_i2j, valid_match_j, Q_j`` (residuals over
        the pixels of j, reference pixel in i) and block (j ← i) with ``idx_j2i,
        valid_match_i, Q_i``.

        Args:
            pixels: (N,) the pixels (of each block's j) to keep; None keeps all H·W.
            window: a :class:`SolveWindow`, or None for every edge: then only the edges with
                both ends in ``window.keyframes`` and at least one moved are kept, and
                ``ii``/``jj`` are positions in ``window.keyframes``, not keyframe indices.

        Returns:
            namespace with ii (D,), jj (D,) int64, idx (D, N) int64, valid (D, N) bool,
            Q (D, N) float64, D = 2E.
        """
        edges = [e for e in self.edges if min(e.i, e.j) >= first]
        ends = lambda e: (e.i, e.j)
        if window is not None:
            pos = {int(k): n for n, k in enumerate(window.keyframes)}
            ends = lambda e: (pos[e.i], pos[e.j])
            edges = [
                e
                for e in edges
                if e.i in pos and e.j in pos and max(pos[e.i], pos[e.j]) >= window.pin
            ]
        if not edges:
            z = np.zeros(0, dtype=np.int64)
            empty = (np.zeros((0, 0), np.int64), np.zeros((0, 0), bool), np.zeros((0, 0)))
            return SimpleNamespace(ii=z, jj=z, idx=empty[0], valid=empty[1], Q=empty[2])
        cols = slice(None) if pixels is None else pixels
        stack = lambda name: np.stack([getattr(e, name)[cols] for e in edges])
        ii, jj, idx, valid, Q = backend.directed_blocks(
            np.array([ends(e)[0] for e in edges], np.int64),
            np.array([ends(e)[1] for e in edges], np.int64),
            stack("idx_i2j"),
            stack("idx_j2i"),
            stack("valid_match_j"),
            stack("valid_match_i"),
            stack("Q_j"),
            stack("Q_i"),
        )
        return SimpleNamespace(ii=ii, jj=jj, idx=idx, valid=valid, Q=Q)
