"""Paper §3.6 (docs/upstream.md §9) — relocalisation after tracking is lost.

While the system is lost, every new frame gets a mono pointmap and is compared against the
keyframes through the retrieval database (query only, ``retrieval.k`` candidates above
``retrieval.min_thresh``). If there are candidates, the frame is appended *temporarily* as a
keyframe and edges to the candidates are made with the stricter ``reloc.min_match_frac = 0.3``.
On success the frame is inserted into the retrieval database, takes the pose of the best-scoring
accepted candidate (upstream copies it), and the global backend runs, which moves it into place.
On failure the keyframe is removed again and the database is unchanged.

Strictness (a deliberate difference from upstream). Upstream's ``reloc.strict`` rejects the
relocalisation when *any* candidate edge fails. That relies on ASMK with a 64k-word codebook,
whose scores for unrelated images are ~0, so every candidate above ``min_thresh`` is a real
revisit. Our stand-in retrieval only ranks: every view of a room scores 0.01-0.2
(docs/evaluation.md), so with ``k = 3`` the candidates are simply the three best keyframes, and
a frame had to overlap all three by 30 % — with few keyframes, all of them. That is why the
``detour`` path (then called ``jump``) stayed lost for 14 frames after returning to mapped
space and why a lost RGB-D run never recovered (docs/system.md, "Relocalisation"). Here a
candidate whose edge fails is dropped instead; with ``reloc.strict`` the best-ranked candidate
must pass, without it any one.

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
    from mslam.system.global_opt import loop_verifier, solve_backend

    with system.timer("prior"):
        X, C = system.prior.mono(frame)
        p = system.prior.pair(frame, frame)
    features = system.retrieval.features(p.D_ii, p.Q_ii)
    candidates = system.retrieval.query(features)
    if not candidates:
        return False
    n = system.new_keyframe(frame, sim3.identity(), X, C, p.D_ii, p.Q_ii)
    before = len(system.graph.edges)
    system.graph.add_factors(
        ii=[n] * len(candidates),
        jj=list(candidates),
        store=system.keyframes,
        prior=system.prior,
        kernels=system.kernels,
        matching_cfg=system.matching_cfg,
        Q_conf=system.backend_cfg.Q_conf,
        min_match_frac=system.cfg.reloc.min_match_frac,
        is_reloc=False,
        kind="reloc",
        stride=system.cfg.backend_pixel_stride(system.keyframes[n].shape),
        verify=loop_verifier(system, check_rotation=False),
    )
    accepted = [e.j for e in system.graph.edges[before:]]
    if not accepted or (system.cfg.reloc.strict and candidates[0] not in accepted):
        system.graph.remove_keyframe(n)
        system.keyframes.pop_last()
        return False
    system.retrieval.update(features)  # query + insert: the database id becomes n
    kf = system.keyframes[n]
    best = next(c for c in candidates if c in accepted)
    kf.T_WC = system.keyframes[best].T_WC.copy()
    kf.T_WC_init = kf.T_WC.copy()
    with system.timer("backend"):
        solve_backend(system)
    return True
