"""Paper §3.6 (docs/upstream.md §9) — relocalisation after tracking is lost.

While the system is lost, every new frame gets a mono pointmap and is compared against the
keyframes through the retrieval database (query only, ``retrieval.k`` candidates above
``retrieval.min_thresh``). If there are candidates, the frame is appended *temporarily* as a
keyframe and edges to the candidates are made with the stricter ``reloc.min_match_frac = 0.3``;
with ``reloc.strict`` one rejected edge rejects the relocalisation. On success the frame is
inserted into the retrieval database, takes the pose of the best-scoring candidate (upstream
copies it), and the global backend runs, which moves it into place. On failure the keyframe is
removed again and the database is unchanged.

Public names, in reading order:
    relocalise
"""

from __future__ import annotations

from typing import Any

from mslam.datasets.frame import Frame
from mslam_ref import sim3

__all__ = ["relocalise"]


def relocalise(system: Any, frame: Frame) -> bool:
    """Try to relocalise ``frame``; True (and a new keyframe, the last one) on success.

    Upstream: main.py::relocalization. Paper: §3.6.

    Args:
        system: the :class:`~mslam.system.SlamSystem` (keyframes, graph, retrieval, prior,
            kernels, configs).
        frame: the current frame.

    Returns:
        whether the frame was relocalised.
    """
    from mslam.system.backend_step import solve_backend

    with system.timer("prior"):
        X, C = system.prior.mono(frame)
        p = system.prior.pair(frame, frame)
    features = system.retrieval.features(p.D_ii, p.Q_ii)
    candidates = system.retrieval.query(features)
    if not candidates:
        return False
    n = system.new_keyframe(frame, sim3.identity(), X, C, p.D_ii, p.Q_ii)
    ok = system.graph.add_factors(
        ii=[n] * len(candidates),
        jj=list(candidates),
        store=system.keyframes,
        prior=system.prior,
        kernels=system.kernels,
        matching_cfg=system.matching_cfg,
        Q_conf=system.backend_cfg.Q_conf,
        min_match_frac=system.cfg.reloc.min_match_frac,
        is_reloc=system.cfg.reloc.strict,
        kind="reloc",
    )
    if not ok:
        system.graph.remove_keyframe(n)
        system.keyframes.pop_last()
        return False
    system.retrieval.update(features)  # query + insert: the database id becomes n
    kf = system.keyframes[n]
    kf.T_WC = system.keyframes[candidates[0]].T_WC.copy()
    kf.T_WC_init = kf.T_WC.copy()
    with system.timer("backend"):
        solve_backend(system)
    return True
