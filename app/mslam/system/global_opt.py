"""Paper §3.5 (docs/upstream.md §1.5, §7.3, §8) — the map and the global backend.

:class:`Backend` owns the map — the keyframes, the factor graph and the retrieval index — and
does what a new keyframe triggers. Upstream runs this in a backend process; in single-thread
mode the frontend waits for it. Here it is a plain method call after every new keyframe (and
after a relocalisation), made by the frontend or, with ``single_thread: False``, by
``mslam.system.worker``:

1. candidates for the new keyframe ``k``: the previous keyframe ``k - 1`` (``n_consec = 1``)
   plus the retrieval database's answer (query, then insert ``k``; ``retrieval.k``,
   ``retrieval.min_thresh``), deduplicated, without ``k``;
2. ``FactorGraph.add_factors(ii=candidates, jj=[k]·n, min_match_frac=local_opt.min_match_frac)``;
3. the global Gauss–Newton over all keyframes with edges (first one fixed), through the kernel
   set's ``backend.solve``, on the residuals of a pixel grid (``local_opt.pixels_per_edge``,
   every pixel by default); the poses are written back. With ``local_opt.window_size`` below
   the map's keyframes, only the most recent ones and the new keyframe's loop partners move,
   against their fixed neighbours (``FactorGraph.window``).

All of it happens inside the current map (``map_start`` on, ``mslam.system.recovery``): the
keyframes of earlier maps get no new edge and keep their poses, until a merge
(``mslam.system.merge``) joins the current map to an earlier one, or a relocalisation into an
earlier map (``mslam.system.reloc``) makes that map current again (``in_map``). After each
step the current map's keyframes go through the divergence watch's spread test
(``DivergenceMonitor.check_map``).

Public names, in reading order:
    Backend, residual_grid
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from mslam.config import SlamConfig
from mslam.datasets.frame import Frame
from mslam.kernels import KernelSet
from mslam.priors.base import Prior, is_metric
from mslam.system.divergence import DivergenceMonitor, guard_backend
from mslam.system.edges import Edge, EdgeBuilder, KnownPairs
from mslam.system.graph import FactorGraph
from mslam.system.keyframes import Keyframe, KeyframeStore
from mslam.system.loop_verify import LoopVerifyConfig, verify_edge
from mslam.system.retrieval_features import RetrievalIndex
from mslam.system.state import RunStats
from mslam.system.tracker import flat
from mslam_ref import backend, fusion
from mslam_ref.conventions import FloatArray
from mslam_ref.pointmap import strided_pixels

__all__ = ["Backend", "residual_grid"]


def residual_grid(shape: tuple[int, int], stride: int) -> np.ndarray:
    """(H·W,) bool: the pixels that carry a residual, a regular grid of ``stride`` (all if 1).

    Every pixel of a keyframe pointmap is a residual upstream, so a solve grows with the
    resolution times the number of edges; ``local_opt.pixels_per_edge`` caps the pixels per
    directed block (``SlamConfig.backend_pixel_stride``).
    """
    return strided_pixels(*shape, stride).reshape(-1)


class Backend:
    """The map (keyframes, graph, retrieval) and the global solve (module docstring).

    Args:
        cfg: the run configuration.
        kernels: the kernel set (``matching.match``, ``backend.solve``).
        prior: the prior (shared with the frontend; serialised when the backend has a thread).
        K: (3, 3) intrinsics in calibrated mode, else None.
        stats: the run's counters and stage timers.
        divergence: the run's divergence watch (a solve that would diverge is undone).
    """

    def __init__(
        self,
        cfg: SlamConfig,
        kernels: KernelSet,
        prior: Prior,
        K: FloatArray | None,
        stats: RunStats,
        divergence: DivergenceMonitor,
    ) -> None:
        self.cfg, self.kernels, self.K, self.stats = cfg, kernels, K, stats
        self.divergence = divergence
        self.prior = prior
        self.backend_cfg = cfg.backend()
        self.fusion_cfg = cfg.fusion()
        self.lock = threading.RLock()  # keyframes shared with the background backend
        self.keyframes = KeyframeStore()
        self.graph = FactorGraph()
        self.retrieval = RetrievalIndex(cfg.retrieval())
        self.edges = EdgeBuilder(
            self.keyframes, prior, kernels, cfg.matching(), self.backend_cfg.Q_conf
        )
        self.history: list[dict[str, Any]] = []
        #: Every loop-closure verdict (``i``, ``j``, ``accepted``, the fit's statistics).
        self.loop_checks: list[dict[str, Any]] = []
        #: The first keyframe of the current map (``mslam.system.recovery``).
        self.map_start = 0
        #: Keyframe ranges ``[a, b)`` after ``map_start`` that are not in the current map (maps
        #: that a merge passed over, ``mslam.system.merge``).
        self.excluded: list[tuple[int, int]] = []

    def start_map(self) -> None:
        """The next keyframe starts a new map: edges, solves and relocalisation stay in it."""
        self.map_start, self.excluded = len(self.keyframes), []

    def join_map(self, first: int, excluded: list[tuple[int, int]]) -> None:
        """The current map continues the one that starts at keyframe ``first`` (a merge,
        ``mslam.system.merge``): edges, solves and relocalisation reach back to it, except to
        the keyframe ranges ``excluded`` (other maps in between)."""
        self.map_start, self.excluded = int(first), [(int(a), int(b)) for a, b in excluded]

    def in_map(self, k: int) -> bool:
        """Whether keyframe ``k`` belongs to the current map."""
        return k >= self.map_start and not any(a <= k < b for a, b in self.excluded)

    def add_keyframe(
        self,
        frame: Frame,
        T_WC: FloatArray,
        X: np.ndarray,
        C: np.ndarray,
        D: np.ndarray,
        Q: np.ndarray,
    ) -> int:
        """Append a keyframe with a fresh pointmap state and its retrieval features.

        Args:
            frame: the input frame; T_WC: (8,) its pose; X (H, W, 3), C (H, W): its pointmap
            and confidence; D (H, W, F), Q (H, W): its descriptors and their confidence.

        Returns:
            the keyframe's index.
        """
        shape = (int(X.shape[0]), int(X.shape[1]))
        state = fusion.init_pointmap(flat(X), flat(C), self.fusion_cfg)
        kf = Keyframe(
            frame=frame,
            T_WC=np.asarray(T_WC, np.float64).copy(),
            state=state,
            shape=shape,
            features=self.retrieval.features(D, Q),
        )
        with self.lock:
            k = self.keyframes.append(kf)
        keep = getattr(self.prior, "keep", None)  # a prior that holds keyframe features (MASt3R)
        if keep is not None:
            keep(frame)
        return k

    def remove_last_keyframe(self) -> None:
        """Undo the last :meth:`add_keyframe` and its edges (a failed relocalisation)."""
        k = len(self.keyframes) - 1
        self.graph.remove_keyframe(k)
        with self.lock:
            kf = self.keyframes.pop_last()
        forget = getattr(self.prior, "forget", None)
        if forget is not None:
            forget(int(kf.frame.index))

    def step(self, k: int, known: KnownPairs | None = None) -> None:
        """Everything a new keyframe ``k`` triggers: its graph edges, then the global solve
        (timed as the ``graph`` and ``backend`` stages). Upstream: main.py::run_backend.

        ``known``: decodes the frontend already made (its last tracking pair), reused.
        """
        with self.stats.timer("graph"):
            self.add_keyframe_edges(k, known)
        with self.stats.timer("backend"):
            self.solve()
        # The spread watch reads the current map's keyframes after any map a merge passed over.
        T_kf = self.keyframes.poses()[max([self.map_start, *(b for _, b in self.excluded)]) :]
        self.divergence.check_map(int(self.keyframes[k].frame.index), T_kf,
                                  self.spread_depths(len(T_kf)))  # fmt: skip

    def spread_depths(self, n: int) -> FloatArray | None:
        """What the spread watch reads beside the last ``n`` keyframes' Sim(3) scales: their
        points' median distance (:meth:`keyframe_depths`) for a prior whose pointmaps have a
        scale of their own, None for a metric one (``metric``: made from depth). In metres a
        keyframe's points already measure the scene, which changes when the camera turns
        towards farther surfaces; only the scale ``s_k`` can drift (benchmarks/RESULTS.md,
        "The spread watch with depth")."""
        return None if is_metric(self.prior) else self.keyframe_depths(n)

    def keyframe_depths(self, n: int) -> FloatArray:
        """(n,) median distance of the canonical points of the last ``n`` keyframes to their
        camera, for the spread watch; only its window's keyframes are measured (NaN before)."""
        depth = np.full(n, np.nan)
        for i in range(max(0, n - self.divergence.cfg.spread_window - 1), n):
            X = self.keyframes[len(self.keyframes) - n + i].state.X_canon
            depth[i] = float(np.median(np.linalg.norm(np.reshape(X, (-1, 3)), axis=1)))
        return depth

    def add_keyframe_edges(self, k: int, known: KnownPairs | None = None) -> int:
        """Graph construction for new keyframe ``k``; returns the number of edges added.

        Upstream: main.py::run_backend (candidate list), global_opt.py::FactorGraph.add_factors.
        """
        kf = self.keyframes[k]
        candidates = [k - 1] if k >= 1 else []
        candidates += self.retrieval.update(kf.retrieval_features())
        seen: list[int] = []
        for c in candidates:
            if c != k and c not in seen and self.in_map(c) and c < len(self.keyframes):
                seen.append(int(c))
        if not seen:
            return 0
        before = len(self.graph)
        self.graph.add_factors(
            self.edges,
            ii=seen,
            jj=[k] * len(seen),
            min_match_frac=self.backend_cfg.min_match_frac,
            known=known,
            stride=self.cfg.backend_pixel_stride(kf.shape),
            verify=self.loop_verifier(),
        )
        return len(self.graph) - before

    def loop_verifier(self, check_rotation: bool = True) -> Callable[[Edge], bool]:
        """``edge -> bool``: :func:`mslam.system.loop_verify.verify_edge` on the keyframes;
        each verdict is appended to :attr:`loop_checks`. ``check_rotation=False`` for a
        relocalisation, whose new keyframe has no pose yet."""
        cfg = (
            LoopVerifyConfig() if check_rotation else replace(LoopVerifyConfig(), max_rot_deg=180.0)
        )

        def verify(edge: Edge) -> bool:
            ok, stats = verify_edge(edge, self.keyframes, self.backend_cfg.Q_conf, cfg)
            self.loop_checks.append({"i": int(edge.i), "j": int(edge.j), "accepted": ok, **stats})
            return ok

        return verify

    def solve(self) -> dict[str, Any] | None:
        """Global Gauss–Newton over every keyframe with an edge; writes the poses back.

        Upstream: global_opt.py::FactorGraph.solve_GN_rays / solve_GN_calib (docs/upstream.md
        §8). Pointmaps are ray-constrained first in calibrated mode. Returns a record of the
        solve (or None when the graph has no edge).
        """
        with self.lock:  # one consistent snapshot (the frontend may be adding a keyframe)
            T_WC = self.keyframes.poses()
            factors = self.graph
            if self.excluded:  # leave the maps a merge passed over out of the solve
                factors = FactorGraph(
                    [e for e in factors.edges if self.in_map(e.i) and self.in_map(e.j)]
                )
            win = factors.window(len(T_WC), self.backend_cfg.window_size, self.map_start)
            X, C = self.keyframes.pointmaps(fusion, self.K, indices=win.keyframes)
        stride = self.cfg.backend_pixel_stride(X.shape[1:3])
        pixels = None if stride == 1 else np.flatnonzero(residual_grid(X.shape[1:3], stride))
        blocks = factors.two_way_blocks(pixels, self.map_start, win if win.windowed else None)
        if len(blocks.ii) == 0:
            return None
        graph = backend.pose_graph(
            X, C, blocks.ii, blocks.jj, blocks.idx, blocks.valid, blocks.Q, self.K, pixels
        )
        cfg = replace(self.backend_cfg, pin=win.pin) if win.windowed else self.backend_cfg
        T_sub, info = self.kernels.backend.solve(T_WC[win.keyframes], graph, cfg)
        T_new = T_WC.copy()  # keyframes outside the window keep their poses
        T_new[win.keyframes] = np.asarray(T_sub, dtype=np.float64)
        costs, dcfg = tuple(info.costs), self.divergence.cfg
        why = guard_backend(T_WC, T_new, costs, dcfg)
        if why is not None:  # keep the poses the solve started from (mslam.system.divergence)
            minor = guard_backend(T_WC, T_new, costs, dcfg, dcfg.warn_cost_rise) is None
            self.divergence.events.append(
                {"frame": -1, "kind": "solve", "reason": f"backend undone: {why}", "minor": minor}
            )
            T_new = T_WC
        with self.lock:
            self.keyframes.set_poses(T_new, np.arange(len(T_new)))
        self.stats.backend_solves += 1
        record = {
            "keyframes": len(self.keyframes),
            "edges": len(self.graph),
            "iterations": info.iterations,
            "cost": info.cost,
            "step_norms": list(info.step_norms),
            "failed": info.failed,
            "undone": why,
        }
        self.history.append(record)
        return record
