"""Paper §3.4–3.5 (docs/upstream.md §1.3, §7.3–7.4) — keyframes, graph edges, edge acceptance, two-way blocks.

The keyframe store holds, per keyframe, the input frame, its Sim(3) pose ``T_WC``, its fused
canonical pointmap (``PointmapState``) and its retrieval features. Unlike upstream's
``SharedKeyframes`` (512 slots preallocated on the GPU, the cause of the out-of-memory reports
of docs/upstream.md §14) it is a Python list that grows one keyframe at a time.

An edge (i, j) between two keyframes is made like upstream's ``FactorGraph.add_factors``:
the prior decodes the pair both ways, ``pair(i, j)`` and ``pair(j, i)``, matching runs on both
directions in one call per edge, and the per-pixel match quality
``Q_j[n] = sqrt(Q_ii[idx_i2j[n]] · Q_ji[n])`` (and ``Q_i`` likewise) decides the edge's match
fraction ``min(mean(valid_j), mean(valid_i))`` with ``valid = valid_match ∧ Q > Q_conf``. An
edge is rejected when that fraction is below ``min_match_frac`` **unless it is consecutive**
(``i == j - 1``, always accepted). In strict mode (relocalisation) a single rejected edge
rejects them all. Each stored edge gives two directed residual blocks for the backend
(``two_way_blocks``).

Public names, in reading order:
    Keyframe, KeyframeStore, Edge, match_pairs, cannot_pass, match_decoded, FactorGraph
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np

from mslam.datasets.frame import Frame
from mslam_ref import backend
from mslam_ref.conventions import BoolArray, FloatArray, IntArray
from mslam_ref.pointmap import strided_pixels

__all__ = [
    "Edge",
    "FactorGraph",
    "Keyframe",
    "KeyframeStore",
    "cannot_pass",
    "match_decoded",
    "match_pairs",
]


@dataclass(eq=False)
class Keyframe:
    """One keyframe (upstream frame.py::Frame as stored in ``SharedKeyframes``).

    Attributes:
        frame: the input frame (index, timestamp, rgb, ...).
        T_WC: (8,) Sim(3) camera-to-world pose, updated by the backend.
        state: the fused canonical pointmap (``mslam_ref.fusion.PointmapState``: X_canon (N, 3),
            C (N,) accumulated confidence, N, N_updates, score).
        shape: (H, W) of the pointmap.
        features: (nfeat, F) retrieval features, or None.
        T_WC_init: (8,) the pose the keyframe was created with (tracking or relocalisation,
            before any backend solve), kept for plots and diagnostics.
    """

    frame: Frame
    T_WC: FloatArray
    state: Any
    shape: tuple[int, int]
    features: FloatArray | None = None
    T_WC_init: FloatArray | None = None

    def __post_init__(self) -> None:
        if self.T_WC_init is None:
            self.T_WC_init = np.asarray(self.T_WC, dtype=np.float64).copy()


class KeyframeStore:
    """Keyframes in creation order; grows one at a time (no preallocated buffer).

    Upstream: frame.py::SharedKeyframes (``append``, ``pop_last``, ``last_keyframe``,
    ``update_T_WCs``).
    """

    def __init__(self) -> None:
        self._kfs: list[Keyframe] = []

    def __len__(self) -> int:
        return len(self._kfs)

    def __getitem__(self, i: int) -> Keyframe:
        return self._kfs[i]

    def __iter__(self):
        return iter(self._kfs)

    def append(self, kf: Keyframe) -> int:
        """Add a keyframe; returns its index."""
        if self._kfs and kf.shape != self._kfs[0].shape:
            raise ValueError(f"kf: pointmap shape {kf.shape} differs from {self._kfs[0].shape}")
        self._kfs.append(kf)
        return len(self._kfs) - 1

    def pop_last(self) -> Keyframe:
        """Remove and return the last keyframe (a failed relocalisation)."""
        return self._kfs.pop()

    def last(self) -> Keyframe:
        """The most recent keyframe (upstream ``last_keyframe``)."""
        return self._kfs[-1]

    def poses(self) -> FloatArray:
        """(K, 8) Sim(3) poses of all keyframes."""
        return np.stack([kf.T_WC for kf in self._kfs]) if self._kfs else np.zeros((0, 8))

    def set_poses(self, T_WC: FloatArray, indices: IntArray | None = None) -> None:
        """Write back poses (upstream ``update_T_WCs``); ``indices`` default to all."""
        T_WC = np.asarray(T_WC, dtype=np.float64)
        indices = np.arange(len(self._kfs)) if indices is None else np.asarray(indices)
        for k, T in zip(indices, T_WC, strict=True):
            self._kfs[int(k)].T_WC = T.copy()

    def pointmaps(self, fusion: Any, K: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """Stacked canonical pointmaps and average confidences of all keyframes.

        Args:
            fusion: the ``mslam_ref.fusion`` module (for ``average_confidence``).
            K: (3, 3) intrinsics in calibrated mode: points are constrained to the known rays
                (``mslam_ref.calib.constrain_points_to_ray``), as upstream's ``solve_GN_calib``.

        Returns:
            X (K, H, W, 3) and C (K, H, W) = C / N.
        """
        H, W = self._kfs[0].shape
        X = np.stack([kf.state.X_canon.reshape(H, W, 3) for kf in self._kfs])
        C = np.stack(
            [np.asarray(fusion.average_confidence(kf.state)).reshape(H, W) for kf in self._kfs]
        )
        if K is not None:
            from mslam_ref.calib import constrain_points_to_ray

            X = np.stack([constrain_points_to_ray(x, K) for x in X])
        return X, C


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


def _flat(a: np.ndarray, trailing: int = 0) -> np.ndarray:
    return a.reshape(-1, *a.shape[a.ndim - trailing :]) if trailing else a.reshape(-1)


def match_pairs(
    store: KeyframeStore,
    ii: list[int],
    jj: list[int],
    prior: Any,
    kernels: Any,
    matching_cfg: Any,
    Q_conf: float,
) -> list[Edge]:
    """Decode and match keyframe pairs both ways; returns unfiltered candidate edges.

    Upstream: mast3r_utils.py::mast3r_decode_symmetric_batch, mast3r_match_symmetric;
    global_opt.py::FactorGraph.add_factors (steps 1-4, docs/upstream.md §7.3).

    Args:
        store: the keyframes.
        ii, jj: (E,) keyframe index pairs.
        prior: a ``Prior`` (``pair(frame_i, frame_j) -> PairPrediction``).
        kernels: the kernel set (uses ``kernels.matching.match``).
        matching_cfg: ``MatchingConfig``.
        Q_conf: quality threshold of the validity mask (``local_opt.Q_conf``).

    Returns:
        one :class:`Edge` per pair, ``kind`` left at its default.
    """
    if len(ii) != len(jj):
        raise ValueError(f"ii, jj: lengths differ ({len(ii)} != {len(jj)})")
    fwd = [prior.pair(store[i].frame, store[j].frame) for i, j in zip(ii, jj)]
    return match_decoded(store, ii, jj, fwd, prior, kernels, matching_cfg, Q_conf)


def cannot_pass(p: Any, Q_conf: float) -> bool:
    """True when no pixel of the decoded pair ``p`` can reach a match quality above ``Q_conf``.

    Every ``Q_j[n] = sqrt(Q_ii[idx_i2j[n]] · Q_ji[n]) <= sqrt(max Q_ii · max Q_ji)``, so when that
    bound is at most ``Q_conf`` the edge's match fraction is 0 whatever the matcher finds (a
    prior that failed on the pair says so with a tiny ``Q_ji``). Deciding this before the
    backward decode and the matching is an early exit with the same outcome.
    """
    return float(np.sqrt(np.max(p.Q_ii) * np.max(p.Q_ji))) <= Q_conf


def match_decoded(
    store: KeyframeStore,
    ii: list[int],
    jj: list[int],
    fwd: list[Any],
    prior: Any,
    kernels: Any,
    matching_cfg: Any,
    Q_conf: float,
    known: dict[tuple[int, int], Any] | None = None,
    stride: int = 1,
) -> list[Edge]:
    """:func:`match_pairs` given the forward decodes ``fwd[e] = prior.pair(i, j)``.

    ``stride > 1`` matches only the pixels of the backend's residual grid
    (``mslam_ref.pointmap.strided_pixels``; ``local_opt.pixels_per_edge``): the other pixels'
    points are zeroed, which the matcher skips (their matches are never valid, and the solve
    never reads them), and the match fraction is taken over the grid.

    ``known`` maps (frame index of i, frame index of j) to a decode ``prior.pair`` already
    returned for those frames (the frontend's last tracking pair). For a prior whose ``pair``
    is a function of the two frames (synthetic, RGB-D, MASt3R) reusing it is exact; the
    two-view prior remembers depths across pairs, so there a skipped decode changes what it
    remembers (still a valid decode of the pair).
    """
    from mslam_ref.tracking import match_quality

    known = known or {}
    edges = []
    grid = None
    for e, (i, j) in enumerate(zip(ii, jj)):
        p = fwd[e]
        fi, fj = store[j].frame, store[i].frame
        q = known.get((int(fi.index), int(fj.index))) or prior.pair(fi, fj)  # X_jj, X_ij in j
        if grid is None:
            grid = strided_pixels(*p.X_ii.shape[:2], stride)
        X_ji = np.stack([p.X_ji, q.X_ji])
        if stride > 1:
            X_ji = np.where(grid[None, ..., None], X_ji, 0.0)
        # One call for both directions: pair 0 gives idx_i2j, pair 1 idx_j2i. Edge by edge
        # (not all edges in one batch): the stacked descriptors of 2E pairs were the run's
        # memory peak at 512x384 (38 MB per pair and copy).
        idx, valid = kernels.matching.match(
            np.stack([p.X_ii, q.X_ii]),
            X_ji,
            np.stack([p.D_ii, q.D_ii]),
            np.stack([p.D_ji, q.D_ji]),
            None,
            matching_cfg,
        )
        idx = np.asarray(idx, dtype=np.int64)
        valid = np.asarray(valid, dtype=bool).reshape(idx.shape)
        Q_j = match_quality(_flat(p.Q_ii), _flat(p.Q_ji), idx[0])
        Q_i = match_quality(_flat(q.Q_ii), _flat(q.Q_ji), idx[1])
        on = grid.reshape(-1)
        frac_j = float(np.mean((valid[0] & (Q_j > Q_conf))[on]))
        frac_i = float(np.mean((valid[1] & (Q_i > Q_conf))[on]))
        edges.append(
            Edge(int(i), int(j), idx[0], idx[1], valid[0], valid[1], Q_j, Q_i, min(frac_j, frac_i))
        )
    return edges


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
        ii: list[int],
        jj: list[int],
        store: KeyframeStore,
        prior: Any,
        kernels: Any,
        matching_cfg: Any,
        Q_conf: float,
        min_match_frac: float,
        is_reloc: bool = False,
        kind: str = "retrieval",
        known: dict[tuple[int, int], Any] | None = None,
        stride: int = 1,
        verify: Any = None,
    ) -> bool:
        """Match candidate pairs and store the accepted edges; True if at least one was added.

        Upstream: global_opt.py::FactorGraph.add_factors (docs/upstream.md §7.3).

        Acceptance: an edge is invalid when ``match_frac < min_match_frac`` and it is not
        consecutive (``i == j - 1``); with ``is_reloc`` (strict) any invalid edge rejects all.
        Consecutive edges get ``kind = "consecutive"``, the others ``kind``. ``known``: decodes
        already made, and ``stride``, the residual grid to match, as in :func:`match_decoded`.
        ``verify(edge) -> bool``, when given, must also accept each non-consecutive edge
        (``mslam.system.loop_verify``); its refusals are counted in ``candidates_unverified``.
        """
        fwd = [prior.pair(store[i].frame, store[j].frame) for i, j in zip(ii, jj)]
        # Early exit: a non-consecutive candidate whose forward decode cannot pass the quality
        # gate would be rejected after matching; it is rejected now, unmatched.
        doomed = [
            i != j - 1 and min_match_frac > 0 and cannot_pass(p, Q_conf)
            for i, j, p in zip(ii, jj, fwd)
        ]
        self.candidates_tested += len(ii)
        self.candidates_rejected_early += sum(doomed)
        if is_reloc and any(doomed):
            return False
        ii, jj, fwd = ([x for x, d in zip(seq, doomed) if not d] for seq in (ii, jj, fwd))
        candidates = match_decoded(
            store, ii, jj, fwd, prior, kernels, matching_cfg, Q_conf, known, stride
        )
        keep = []
        for e in candidates:
            consecutive = e.i == e.j - 1
            if consecutive:
                e.kind = "consecutive"
            else:
                e.kind = kind
            ok = consecutive or e.match_frac >= min_match_frac
            if ok and not consecutive and verify is not None and not verify(e):
                ok, self.candidates_unverified = False, self.candidates_unverified + 1
            keep.append(ok)
        if is_reloc and not all(keep):
            return False
        added = [e for e, k in zip(candidates, keep) if k]
        self.edges.extend(added)
        return bool(added)

    def remove_keyframe(self, k: int) -> None:
        """Drop every edge touching keyframe ``k`` (used when a relocalisation is undone)."""
        self.edges = [e for e in self.edges if k not in (e.i, e.j)]

    def count(self, kind: str) -> int:
        """Number of stored edges of one kind."""
        return sum(e.kind == kind for e in self.edges)

    def two_way_blocks(self, pixels: IntArray | None = None) -> SimpleNamespace:
        """Directed residual blocks of all edges (upstream ``prep_two_way_edges``, docs/upstream.md §7.4).

        Edge (i, j) gives block (i ← j) with ``idx_i2j, valid_match_j, Q_j`` (residuals over
        the pixels of j, reference pixel in i) and block (j ← i) with ``idx_j2i,
        valid_match_i, Q_i``.

        Args:
            pixels: (N,) the pixels (of each block's j) to keep; None keeps all H·W.

        Returns:
            namespace with ii (D,), jj (D,) int64, idx (D, N) int64, valid (D, N) bool,
            Q (D, N) float64, D = 2E.
        """
        if not self.edges:
            z = np.zeros(0, dtype=np.int64)
            empty = (np.zeros((0, 0), np.int64), np.zeros((0, 0), bool), np.zeros((0, 0)))
            return SimpleNamespace(ii=z, jj=z, idx=empty[0], valid=empty[1], Q=empty[2])
        cols = slice(None) if pixels is None else pixels
        stack = lambda name: np.stack([getattr(e, name)[cols] for e in self.edges])
        ii, jj, idx, valid, Q = backend.directed_blocks(
            [e.i for e in self.edges],
            [e.j for e in self.edges],
            stack("idx_i2j"),
            stack("idx_j2i"),
            stack("valid_match_j"),
            stack("valid_match_i"),
            stack("Q_j"),
            stack("Q_i"),
        )
        return SimpleNamespace(ii=ii, jj=jj, idx=idx, valid=valid, Q=Q)
