"""Map merging — a new map joins the earlier one when the camera returns to it.

A new map (``mslam.system.recovery``) starts at the pose of the last posed frame, so how it
sits relative to the earlier maps is only a guess. While the current map (a *segment*: the
maps merged so far, ``mslam.system.recovery``) does not start at map 0, every new keyframe
``k`` of it looks for the earlier maps' keyframes it sees:

1. **retrieval** — the retrieval database's scores of ``k``'s features against every keyframe
   before the current segment's first (``MergeConfig.candidates`` best with a score above
   ``retrieval.min_thresh``);
2. **edges** — each candidate pair is decoded and matched both ways as every graph edge is
   (``EdgeBuilder.decode`` and ``match``, after the early exit of ``edges.cannot_pass``); the
   edge's match fraction must reach relocalisation's
   (``reloc.min_match_frac``) or ``MergeConfig.min_match_frac``, whichever is stricter;
3. **verification** — the matched canonical points must fit one similarity
   (``mslam.system.loop_verify.fit_edge``): at least ``min_inlier_frac`` inliers, above the
   loop closure's share, with no rotation test (the two maps' poses are unrelated);
4. **correction** — a verified edge (new keyframe ``i``, old keyframe ``j``) with the fit
   ``T_CiCj`` (camera j's points in camera i) puts keyframe ``i`` where the old map says it
   is, ``T_WCi' = T_WCj · T_CiCj⁻¹``; the same Sim(3) for the whole new segment is
   ``S = T_WCj · T_CiCj⁻¹ · T_WCi⁻¹`` (old map's world ← new map's world);
5. **agreement** — one connection can be wrong (a repeated texture, a prior that fails on a
   far-apart pair), so a merge needs ``min_support`` verified connections (kept across the
   segment's keyframes, their corrections recomputed from the current poses) whose
   corrections agree (and whose old keyframes lie in one earlier segment): rotations within
   ``max_rot_deg``, scales within a factor ``max_scale_ratio``, and the new keyframes' centres
   put within ``max_move_frac`` of the old keyframe's scene depth of each other.

Then the merge: every keyframe of the current segment is moved by the agreeing connection
with the most inliers' ``S`` (frame poses are stored relative to keyframes and follow), the
connections' edges enter the graph (kind ``"merge"``), ``Recovery.merged`` records it, and the
backend's map becomes the union (``Backend.join_map`` with ``Recovery.layout``): it reaches
back to the earlier segment's first keyframe, which the solve holds fixed, so the earlier map
stays where it was; maps between the two that are not part of either (maps a merge passes
over, e.g. a map started while the camera saw nothing) are left out of edges, solves and
relocalisation (``Backend.in_map``), so every solve's graph stays connected and anchored.
Then the global solve runs.

Public names, in reading order:
    MergeConfig, Connection, correction, agree, MapMerger
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mslam.system.edges import Edge, cannot_pass
from mslam.system.global_opt import Backend
from mslam.system.keyframes import KeyframeStore
from mslam.system.loop_verify import LoopVerifyConfig, fit_edge
from mslam.system.recovery import Recovery
from mslam_ref import sim3
from mslam_ref.conventions import FloatArray

__all__ = ["Connection", "MapMerger", "MergeConfig", "agree", "correction"]


@dataclass(frozen=True)
class MergeConfig:
    """Thresholds of a merge (module docstring).

    Attributes:
        candidates: keyframes of the earlier segment tried per new keyframe.
        min_match_frac: an edge's match fraction at least this (and ``reloc.min_match_frac``).
        min_inlier_frac: share of an edge's valid matches that fit its similarity.
        min_support: verified connections whose corrections must agree.
        max_rot_deg: largest rotation between two agreeing corrections.
        max_scale_ratio: largest ratio of two agreeing corrections' scales.
        max_move_frac: largest distance between the places two corrections put a new
            keyframe's centre, as a share of the old keyframe's median scene depth.
        verify: the similarity fit's settings (``inlier_rel``, RANSAC).
    """

    candidates: int = 3
    min_match_frac: float = 0.3
    min_inlier_frac: float = 0.4
    min_support: int = 2
    max_rot_deg: float = 15.0
    max_scale_ratio: float = 1.3
    max_move_frac: float = 0.25
    verify: LoopVerifyConfig = field(default_factory=LoopVerifyConfig)


@dataclass
class Connection:
    """A verified edge between a keyframe of the current segment and one of the earlier one.

    Attributes:
        edge: the graph edge (``i``: the new keyframe, ``j``: the old one).
        T_CiCj: (8,) the similarity its matched points fit (camera j's points in camera i).
        inlier_frac: share of its valid matches that fit.
        matches: valid matches used by the fit.
    """

    edge: Edge
    T_CiCj: FloatArray
    inlier_frac: float
    matches: int


def correction(c: Connection, store: KeyframeStore) -> FloatArray:
    """(8,) ``S = T_WCj · T_CiCj⁻¹ · T_WCi⁻¹``: the Sim(3) that moves the new segment (and its
    keyframe ``i``) onto the old one, from the keyframes' current poses."""
    T_WCi, T_WCj = store[c.edge.i].T_WC, store[c.edge.j].T_WC
    return sim3.mul(sim3.mul(T_WCj, sim3.inv(c.T_CiCj)), sim3.inv(T_WCi))


def _rotation_deg(T: FloatArray) -> float:
    """Angle (degrees) of the rotation of an (8,) Sim(3) (its quaternion's ``qw``)."""
    return float(np.degrees(2 * np.arccos(np.clip(abs(T[6]), 0.0, 1.0))))


def _scene_depth(store: KeyframeStore, k: int) -> float:
    """Median distance of keyframe ``k``'s canonical points from its camera, in world units."""
    X = np.reshape(store[k].state.X_canon, (-1, 3))
    return float(np.median(np.linalg.norm(X, axis=1)) * store[k].T_WC[7])


def agree(a: Connection, b: Connection, store: KeyframeStore, cfg: MergeConfig) -> bool:
    """Whether two connections' corrections are one (module docstring, step 5)."""
    Sa, Sb = correction(a, store), correction(b, store)
    d = sim3.mul(sim3.inv(Sa), Sb)
    rot_deg = _rotation_deg(d)
    ratio = max(Sa[7] / Sb[7], Sb[7] / Sa[7])
    depth = min(_scene_depth(store, a.edge.j), _scene_depth(store, b.edge.j))
    centres = np.stack([store[a.edge.i].T_WC[:3], store[b.edge.i].T_WC[:3]])
    move = float(np.max(np.linalg.norm(sim3.act(Sa, centres) - sim3.act(Sb, centres), axis=1)))
    return bool(
        rot_deg <= cfg.max_rot_deg
        and ratio <= cfg.max_scale_ratio
        and move <= cfg.max_move_frac * depth
    )


class MapMerger:
    """Finds the connections of the current segment to the one before it and merges them.

    Args:
        cfg: the thresholds.

    Attributes:
        pending: verified connections of the current segment not yet merged.
        checks: every candidate edge's verdict (``i``, ``j``, ``accepted``, ``matches``,
            ``inlier_frac``, ``match_frac``).
    """

    def __init__(self, cfg: MergeConfig | None = None) -> None:
        self.cfg = cfg or MergeConfig()
        self.pending: list[Connection] = []
        self.checks: list[dict[str, Any]] = []

    def reset(self) -> None:
        """Forget the pending connections (a new map starts)."""
        self.pending = []

    def candidates(self, backend: Backend, k: int, end: int) -> list[int]:
        """Keyframes ``0 .. end - 1`` that retrieval ranks best for keyframe ``k``."""
        db = backend.retrieval.db
        if db is None or end <= 0:
            return []
        scores = np.asarray(db.scores(backend.keyframes[k].retrieval_features()))[:end]
        order = np.argsort(-scores, kind="stable")[: self.cfg.candidates]
        return [int(o) for o in order if scores[o] > backend.retrieval.cfg.min_thresh]

    def connect(
        self, backend: Backend, k: int, end: int, min_match_frac: float
    ) -> list[Connection]:
        """Verified connections of keyframe ``k`` to keyframes ``0 .. end - 1``."""
        cands = self.candidates(backend, k, end)
        if not cands:
            return []
        frac = max(min_match_frac, self.cfg.min_match_frac)
        stride = backend.cfg.backend_pixel_stride(backend.keyframes[k].shape)
        Q_conf = backend.backend_cfg.Q_conf
        ii, jj = [k] * len(cands), cands
        fwd = backend.edges.decode(ii, jj)
        live = [e for e, p in enumerate(fwd) if not cannot_pass(p, Q_conf)]
        self.checks += [{"i": k, "j": jj[e], "accepted": False, "match_frac": 0.0, "matches": 0.0,
                         "inlier_frac": 0.0} for e in range(len(jj)) if e not in live]  # fmt: skip
        ii, jj, fwd = [ii[e] for e in live], [jj[e] for e in live], [fwd[e] for e in live]
        found = []
        for e in backend.edges.match(ii, jj, fwd, None, stride):
            e.kind = "merge"
            T, stats = None, {"matches": 0.0, "inlier_frac": 0.0}
            if e.match_frac >= frac:
                T, stats = fit_edge(e, backend.keyframes, Q_conf, self.cfg.verify)
            ok = T is not None and stats["inlier_frac"] >= self.cfg.min_inlier_frac
            self.checks.append({"i": e.i, "j": e.j, "accepted": ok, "match_frac": e.match_frac,
                                **stats})  # fmt: skip
            if ok and T is not None:
                found.append(Connection(e, T, stats["inlier_frac"], int(stats["matches"])))
        return found

    def agreeing(
        self, store: KeyframeStore, target: Callable[[int], int] | None = None
    ) -> list[Connection] | None:
        """The largest set of pending connections that agree with one of them, if it has
        ``min_support`` members, best first (most inliers); ``target`` (old keyframe ->
        its segment) keeps a set to one earlier segment."""
        seg = target or (lambda j: 0)
        best: list[Connection] | None = None
        for a in self.pending:
            group = [
                b
                for b in self.pending
                if b is a or (seg(b.edge.j) == seg(a.edge.j) and agree(a, b, store, self.cfg))
            ]
            if len(group) >= self.cfg.min_support and (best is None or len(group) > len(best)):
                best = group
        if best is None:
            return None
        return sorted(best, key=lambda c: -c.inlier_frac * c.matches)

    def step(
        self, backend: Backend, recovery: Recovery, k: int, min_match_frac: float
    ) -> FloatArray | None:
        """After keyframe ``k``'s backend step: look for connections, merge when they agree.

        Args:
            backend: the map.
            recovery: the maps' record (``segment_of``, ``merged``, ``layout``).
            k: the new keyframe.
            min_match_frac: ``reloc.min_match_frac``.

        Returns:
            (8,) the correction applied to the current segment, or None (no merge).
        """
        if not recovery.cfg.merge_maps or backend.map_start == 0 or not backend.in_map(k):
            return None
        with backend.stats.timer("merge"):  # the search; the solve after a merge is "backend"
            self.pending += self.connect(backend, k, backend.map_start, min_match_frac)

        def target(j: int) -> int:
            return recovery.segment_of(recovery.map_of(j))

        group = self.agreeing(backend.keyframes, target)
        if group is None:
            return None
        into = target(group[0].edge.j)
        S = correction(group[0], backend.keyframes)
        with backend.lock:
            moved = np.array([c for c in range(len(backend.keyframes)) if backend.in_map(c)])
            backend.keyframes.set_poses(sim3.mul(S, backend.keyframes.poses()[moved]), moved)
            backend.graph.edges.extend(c.edge for c in group)
        rot = _rotation_deg(S)
        recovery.merged({
            "into": into, "frame": int(backend.keyframes[k].frame.index), "keyframe": group[0].edge.i,
            "old_keyframe": group[0].edge.j, "connections": len(group), "scale": float(S[7]),
            "rot_deg": rot, "translation": float(np.linalg.norm(S[:3])), "by": "merge",
        })  # fmt: skip
        backend.join_map(*recovery.layout())
        self.pending = []
        with backend.stats.timer("backend"):
            backend.solve()
        return S
