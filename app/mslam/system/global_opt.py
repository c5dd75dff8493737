"""Paper §3.5 (docs/upstream.md §1.5, §7.3, §8) — graph construction and the global backend, synchronously.

Upstream runs these in a backend process; in single-thread mode the frontend waits for them.
Here they are plain function calls after every new keyframe (and after a relocalisation),
made by the frontend or, with ``single_thread: False``, by ``mslam.system.worker``:

1. candidates for the new keyframe ``k``: the previous keyframe ``k - 1`` (``n_consec = 1``)
   plus the retrieval database's answer (query, then insert ``k``; ``retrieval.k``,
   ``retrieval.min_thresh``), deduplicated, without ``k``;
2. ``FactorGraph.add_factors(ii=candidates, jj=[k]·n, min_match_frac=local_opt.min_match_frac)``;
3. the global Gauss–Newton over all keyframes with edges (first one fixed), through the kernel
   set's ``backend.solve``, on the residuals of a pixel grid (``local_opt.pixels_per_edge``,
   every pixel by default); the poses are written back.

Public names, in reading order:
    backend_step, add_keyframe_edges, loop_verifier, residual_grid, solve_backend
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam.system.divergence import guard_backend
from mslam_ref import backend
from mslam_ref.pointmap import strided_pixels

__all__ = ["add_keyframe_edges", "backend_step", "loop_verifier", "residual_grid", "solve_backend"]


def backend_step(system: Any, k: int) -> None:
    """Everything a new keyframe ``k`` triggers: its graph edges, then the global solve
    (timed as the ``graph`` and ``backend`` stages). Upstream: main.py::run_backend."""
    with system.timer("graph"):
        add_keyframe_edges(system, k)
    with system.timer("backend"):
        solve_backend(system)


def add_keyframe_edges(system: Any, k: int) -> int:
    """Graph construction for new keyframe ``k``; returns the number of edges added.

    Upstream: main.py::run_backend (candidate list), global_opt.py::FactorGraph.add_factors.
    """
    kf = system.keyframes[k]
    candidates = [k - 1] if k >= 1 else []
    candidates += system.retrieval.update(kf.features)
    seen: list[int] = []
    for c in candidates:
        if c != k and c not in seen and 0 <= c < len(system.keyframes):
            seen.append(int(c))
    if not seen:
        return 0
    before = len(system.graph)
    system.graph.add_factors(
        ii=seen,
        jj=[k] * len(seen),
        store=system.keyframes,
        prior=system.prior,
        kernels=system.kernels,
        matching_cfg=system.matching_cfg,
        Q_conf=system.backend_cfg.Q_conf,
        min_match_frac=system.backend_cfg.min_match_frac,
        kind="retrieval",
        known=system.last_pair(),
        stride=system.cfg.backend_pixel_stride(kf.shape),
        verify=loop_verifier(system),
    )
    return len(system.graph) - before


def loop_verifier(system: Any, check_rotation: bool = True):
    """``edge -> bool``: :func:`mslam.system.loop_verify.verify_edge` on the system's keyframes;
    each verdict is appended to ``system.loop_checks`` (``i``, ``j``, accepted, stats).
    ``check_rotation=False`` for a relocalisation, whose new keyframe has no pose yet."""
    from dataclasses import replace

    from mslam.system.loop_verify import LoopVerifyConfig, verify_edge

    cfg = LoopVerifyConfig() if check_rotation else replace(LoopVerifyConfig(), max_rot_deg=180.0)

    checks = system.__dict__.setdefault("loop_checks", [])

    def verify(edge: Any) -> bool:
        ok, stats = verify_edge(edge, system.keyframes, system.backend_cfg.Q_conf, cfg)
        checks.append({"i": int(edge.i), "j": int(edge.j), "accepted": ok, **stats})
        return ok

    return verify


def residual_grid(shape: tuple[int, int], stride: int) -> np.ndarray:
    """(H·W,) bool: the pixels that carry a residual, a regular grid of ``stride`` (all if 1).

    Every pixel of a keyframe pointmap is a residual upstream, so a solve grows with the
    resolution times the number of edges; ``local_opt.pixels_per_edge`` caps the pixels per
    directed block (``SlamConfig.backend_pixel_stride``).
    """
    return strided_pixels(*shape, stride).reshape(-1)


def solve_backend(system: Any) -> dict[str, Any] | None:
    """Global Gauss–Newton over every keyframe with an edge; writes the poses back.

    Upstream: global_opt.py::FactorGraph.solve_GN_rays / solve_GN_calib (docs/upstream.md §8). Pointmaps
    are ray-constrained first in calibrated mode. Returns a record of the solve (or None when
    the graph has no edge).
    """
    with system.lock:  # one consistent snapshot (the frontend may be adding a keyframe)
        T_WC = system.keyframes.poses()
        X, C = system.keyframes.pointmaps(system._fusion_ref, system.K)
    stride = system.cfg.backend_pixel_stride(X.shape[1:3])
    pixels = None if stride == 1 else np.flatnonzero(residual_grid(X.shape[1:3], stride))
    blocks = system.graph.two_way_blocks(pixels)
    if len(blocks.ii) == 0:
        return None
    graph = backend.pose_graph(
        X, C, blocks.ii, blocks.jj, blocks.idx, blocks.valid, blocks.Q, system.K, pixels
    )
    T_new, info = system.kernels.backend.solve(T_WC, graph, system.backend_cfg)
    T_new = np.asarray(T_new, dtype=np.float64)
    why = guard_backend(T_WC, T_new, tuple(info.costs), system.divergence.cfg)
    if why is not None:  # keep the poses the solve started from (mslam.system.divergence)
        system.divergence.events.append({"frame": -1, "reason": f"backend undone: {why}"})
        T_new = T_WC
    with system.lock:
        system.keyframes.set_poses(T_new, np.arange(len(T_new)))
    system.stats.backend_solves += 1
    record = {
        "keyframes": len(system.keyframes),
        "edges": len(system.graph),
        "iterations": info.iterations,
        "cost": info.cost,
        "step_norms": list(info.step_norms),
        "failed": info.failed,
        "undone": why,
    }
    system.backend_history.append(record)
    return record
