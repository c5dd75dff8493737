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
candidate whose edge fails is dropped instead. With ``reloc.strict: True`` the best-ranked
candidate must still pass; the default ``False`` accepts the frame when any candidate passes
the match fraction and the geometric verification (``Backend.loop_verifier``), and places it
at the best-ranked of those. A ranking stand-in often puts a keyframe the frame barely sees
first: on ``synthetic:rotation:60`` (96x72, two-view prior, tracking given up after frame 30)
the strict rule refused every frame until a new map started 55° off; without it frame 31 was
relocalised 3.3° from its true orientation (2026-11-26).

With several maps (``mslam.system.recovery``) the candidates of the current map are tried
first. When none passes, the candidates from other maps are tried the same way, and a frame
accepted there makes the run continue that map (``rejoin``: ``SlamSystem.rejoin_map``; the
map being left keeps its poses and stays apart, as a merge leaves the maps it passes over).
That is how a camera that was lost, started a map somewhere new and came back is taken home:
``mslam.system.merge`` needs two agreeing connections from keyframes of the new map, which a
camera that is lost again at once never makes. ``synthetic:detour`` (72 frames, two-view
prior, 2026-11-27) posed 3 of the 18 frames after its return, 17 with this (3.4 cm from the
truth under the first map's alignment).

A keyframe made under pure rotation has no depth (``mslam.system.rotation_start``), so no
edge to it can be verified; when no edge is accepted, a candidate without depth whose pair
with the frame is a rotation (the prior's ``"parallax"`` verdict with a rotation) is accepted,
and the frame is placed by that rotation about the candidate's centre.

Public names, in reading order:
    relocalise
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mslam.config import RelocConfig
from mslam.datasets.frame import Frame
from mslam.priors.base import PairPrediction, Prior
from mslam.system.global_opt import Backend
from mslam_ref import sim3

__all__ = ["relocalise"]


def relocalise(
    frame: Frame,
    prior: Prior,
    backend: Backend,
    cfg: RelocConfig,
    place: Callable[[int, int], None] | None = None,
    rotation_match: Callable[[int, int], bool] | None = None,
    rejoin: Callable[[int, int], None] | None = None,
) -> bool:
    """Try to relocalise ``frame``; True (and a new keyframe, the last one) on success.

    Upstream: main.py::relocalization. Paper: §3.6.

    Args:
        frame: the current frame.
        prior: its ``mono`` and ``pair`` give the frame's pointmap and descriptors.
        backend: the map (keyframes, graph, retrieval) and the global solve.
        cfg: ``reloc.*`` (``min_match_frac``; ``strict``: the best-ranked candidate must pass).
        place: ``(new keyframe, best candidate) -> None``, run before the solve, may replace
            the copied pose and the pointmap (``ParallaxSteps.place_relocalised``).
        rotation_match: ``(new keyframe, candidate) -> bool``, asked in ranking order when no
            edge is accepted: the first candidate it accepts is (a keyframe without depth,
            whose image the frame's is turned from: ``RotationStart.rotation_match``).
        rejoin: ``(new keyframe, best candidate) -> None``; given, the keyframes of other maps
            are tried when none of the current map's passes, and on success it is called
            (before ``place`` and the solve) to make the candidate's map the current one
            (``SlamSystem.rejoin_map``). None: the current map only.

    Returns:
        whether the frame was relocalised.
    """
    with backend.stats.timer("prior"):
        X, C = prior.mono(frame)
        p = prior.pair(frame, frame)
    features = backend.retrieval.features(p.D_ii, p.Q_ii)
    ranked = backend.retrieval.query(features)
    # The current map first; an earlier map only when none of the current map's candidates
    # passes and the caller can take the frame there (``rejoin``).
    for candidates, other in (
        ([c for c in ranked if backend.in_map(c)], False),
        ([c for c in ranked if not backend.in_map(c)] if rejoin is not None else [], True),
    ):
        best = _attempt(frame, (X, C, p), features, candidates, backend, cfg, rotation_match)
        if best is None:
            continue
        n = len(backend.keyframes) - 1
        if other and rejoin is not None:
            rejoin(n, best)
        if place is not None:
            place(n, best)
        with backend.stats.timer("backend"):
            backend.solve()
        return True
    return False


def _attempt(
    frame: Frame,
    pointmap: tuple[np.ndarray, np.ndarray, PairPrediction],
    features: np.ndarray,
    candidates: list[int],
    backend: Backend,
    cfg: RelocConfig,
    rotation_match: Callable[[int, int], bool] | None,
) -> int | None:
    """The frame as a temporary keyframe with edges to ``candidates`` (ranked best first);
    on success it stays (the last keyframe, in the retrieval database, at the pose of the best
    accepted candidate) and that candidate is returned; otherwise it is removed and None.

    ``pointmap``: the frame's mono ``X`` (H, W, 3), ``C`` (H, W) and its self-pair (``D_ii``,
    ``Q_ii``); ``features``: its retrieval features.
    """
    if not candidates:
        return None
    X, C, p = pointmap
    n = backend.add_keyframe(frame, sim3.identity(), X, C, p.D_ii, p.Q_ii)
    before = len(backend.graph.edges)
    backend.graph.add_factors(
        backend.edges,
        ii=[n] * len(candidates),
        jj=list(candidates),
        min_match_frac=cfg.min_match_frac,
        kind="reloc",
        stride=backend.cfg.backend_pixel_stride(backend.keyframes[n].shape),
        verify=backend.loop_verifier(check_rotation=False),
    )
    accepted = [e.j for e in backend.graph.edges[before:]]
    if not accepted and rotation_match is not None:
        accepted = next(([c] for c in candidates if rotation_match(n, c)), [])
    if not accepted or (cfg.strict and candidates[0] not in accepted):
        backend.remove_last_keyframe()
        return None
    backend.retrieval.update(features)  # query + insert: the database id becomes n
    kf = backend.keyframes[n]
    best = next(c for c in candidates if c in accepted)
    kf.T_WC = backend.keyframes[best].T_WC.copy()
    kf.T_WC_init = kf.T_WC.copy()
    return int(best)
