"""Recovery beyond relocalisation — a new map when the current one cannot be rejoined.

While tracking is lost every frame tries relocalisation (``mslam.system.reloc``). When that
keeps failing, or the divergence watch keeps refusing poses, the frontend gives the map up and
starts a new one from the incoming frames, as at the start of a run:

* ``recovery.max_lost_frames`` consecutive frames without a pose (relocalisation failed on
  each; a *blank* frame, one whose contrast is below ``BLANK_CONTRAST_FRAC`` of the recent
  posed frames' median, neither counts nor breaks the run: a covered lens or a light going out
  shows nothing to relocalise with, not another place, and the frames after it may rejoin the
  map), or
* ``recovery.max_refusals`` frame poses refused by the divergence watch
  (``mslam.system.divergence``) within the last ``recovery.refusal_window`` frames.

Maps are consecutive segments of the keyframe store: map ``m`` holds the keyframes from its
``first_keyframe`` to the next map's. The new map's first keyframe is anchored at the final pose
(rotation, position and Sim(3) scale) of the last frame that had a pose, so the trajectory
stays in one frame of reference and in the TUM format; but how the new map's orientation,
position and scale relate to the old map's is only as good as that one pose. The backend
builds edges and solves inside the current map only, relocalisation searches its keyframes
first (and earlier maps' only when none of them passes: a frame relocalised there makes the run
continue that map, ``Recovery.rejoined``), and the keyframes of earlier maps keep their last
poses — until the maps are
merged (``mslam.system.merge``, ``recovery.merge_maps``): while the current map is not the
first, each of its new keyframes looks for verified connections to the keyframes of earlier
maps, and once two of them agree on one Sim(3) correction, every keyframe of the current map
is moved by that correction (frame poses, stored relative to keyframes, follow), the
connections become graph edges, and the two maps are one for the backend from then on (a
*segment*, named by its first map: a merged map belongs to the segment it was merged into,
and a later merge joins the whole segment to an earlier one; maps in between that neither
joined stay apart, ``layout``). ``summary.json`` says what
happened: ``maps`` (one entry per map: the frame that started it, its first keyframe, frames
posed in it, the reason, and ``merged``: None, or the map it was merged into, at which frame
and keyframe, and the correction's scale, rotation and translation) and one sentence per new
map in ``warnings`` (merged or not, and when).

Public names, in reading order:
    frame_contrast, RecoveryConfig, Recovery
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from mslam.system.state import FramePose, FrameStatus
from mslam_ref.conventions import FloatArray

__all__ = ["BLANK_CONTRAST_FRAC", "Recovery", "RecoveryConfig", "frame_contrast"]

#: A lost frame whose contrast is below this share of the median contrast of the last
#: ``CONTRAST_WINDOW`` posed frames is blank (module docstring). The 7-Scenes kitchen frames
#: have a grey-level standard deviation of 40-70; a covered lens' sensor noise a few units.
BLANK_CONTRAST_FRAC = 0.1
#: Posed frames whose contrast gives the reference of :data:`BLANK_CONTRAST_FRAC`.
CONTRAST_WINDOW = 30


def frame_contrast(rgb: np.ndarray) -> float:
    """Standard deviation of the grey levels (channel mean) of an (H, W, 3) or (H, W) image,
    over every second row and column."""
    a = np.asarray(rgb, dtype=np.float32)[::2, ::2]
    return float(np.std(a.mean(axis=-1) if a.ndim == 3 else a))


@dataclass(frozen=True)
class RecoveryConfig:
    """``recovery.*`` keys (module docstring); 0 turns a trigger off.

    Attributes:
        max_lost_frames: consecutive lost frames that start a new map.
        max_refusals: refused frame poses within ``refusal_window`` frames that start one.
        refusal_window: frames over which refusals are counted.
        merge_maps: 1: a new map is merged into the one before it once verified connections
            agree (``mslam.system.merge``); 0: maps stay apart.
    """

    max_lost_frames: int = 15
    max_refusals: int = 4
    refusal_window: int = 30
    merge_maps: int = 1

    @classmethod
    def from_sections(cls, sections: Mapping[str, Any]) -> RecoveryConfig:
        """From the resolved configuration's ``recovery`` section (missing keys: defaults)."""
        section = dict(sections.get("recovery", {}))
        return cls(**{f.name: int(section[f.name]) for f in fields(cls) if f.name in section})


@dataclass
class Recovery:
    """Counts lost frames and refusals, says when to start a new map, and lists the maps.

    Attributes:
        cfg: the triggers.
        maps: one dict per map: ``map``, ``first_frame`` (the frame that started it; None for
            the first), ``first_keyframe``, ``reason`` (None for the first), ``merged`` (None,
            or the record of :meth:`merged`).
    """

    cfg: RecoveryConfig = field(default_factory=RecoveryConfig)
    maps: list[dict[str, Any]] = field(
        default_factory=lambda: [
            {"map": 0, "first_frame": None, "first_keyframe": 0, "reason": None, "merged": None}
        ]
    )

    def __post_init__(self) -> None:
        self._lost_run = 0
        self._refused: deque[int] = deque()  # frame indices of recent refusals
        self._events_seen = 0
        self._contrast: deque[float] = deque(maxlen=CONTRAST_WINDOW)  # of recent posed frames
        self.blank_frames = 0

    def is_blank(self, contrast: float | None) -> bool:
        """Whether a frame of this ``contrast`` (:func:`frame_contrast`) is blank: below
        :data:`BLANK_CONTRAST_FRAC` of the recent posed frames' median (never before one)."""
        if contrast is None or not self._contrast:
            return False
        return contrast < BLANK_CONTRAST_FRAC * float(np.median(self._contrast))

    def after_frame(
        self, index: int, status: FrameStatus, refused: list[int], contrast: float | None = None
    ) -> str | None:
        """Count frame ``index`` (its ``status`` and its image's ``contrast``, None when
        unknown) and the refusals so far (``refused``: the frame index of every refused pose of
        the run); the reason to start a new map, or None.
        """
        cfg = self.cfg
        if status != FrameStatus.LOST:
            self._lost_run = 0
            if contrast is not None and status != FrameStatus.WAITING:
                self._contrast.append(float(contrast))
        elif self.is_blank(contrast):
            self.blank_frames += 1
        else:
            self._lost_run += 1
        self._refused.extend(refused[self._events_seen :])
        self._events_seen = len(refused)
        while self._refused and self._refused[0] <= index - cfg.refusal_window:
            self._refused.popleft()
        if cfg.max_lost_frames and self._lost_run >= cfg.max_lost_frames:
            return f"{self._lost_run} consecutive frames lost (relocalisation failed on each)"
        if cfg.max_refusals and len(self._refused) >= cfg.max_refusals:
            return (
                f"{len(self._refused)} implausible poses refused within {cfg.refusal_window} frames"
            )
        return None

    def new_map(self, index: int, first_keyframe: int, reason: str) -> None:
        """Record that frame ``index`` starts map ``len(maps)`` at keyframe ``first_keyframe``;
        the counters restart."""
        self.maps.append(
            {"map": len(self.maps), "first_frame": int(index),
             "first_keyframe": int(first_keyframe), "reason": reason, "merged": None}
        )  # fmt: skip
        self._lost_run = 0
        self._refused.clear()

    def rejoined(self, index: int, first_keyframe: int, old_keyframe: int) -> None:
        """Record that frame ``index``, relocalised against keyframe ``old_keyframe`` of
        another map, continues that map's segment: its keyframe ``first_keyframe`` starts map
        ``len(maps)``, merged with no correction (the frame took the old keyframe's pose)."""
        into = self.segment_of(self.map_of(old_keyframe))
        reason = f"tracking was lost and the frame relocalised against keyframe {old_keyframe}"
        self.new_map(index, first_keyframe, f"{reason} of map {into}")
        self.maps[-1]["merged"] = {
            "into": into, "frame": int(index), "keyframe": int(first_keyframe),
            "old_keyframe": int(old_keyframe), "connections": 1, "scale": 1.0, "rot_deg": 0.0,
            "translation": 0.0, "by": "relocalisation",
        }  # fmt: skip

    def segment_of(self, m: int) -> int:
        """The segment of map ``m``, named by its first map: ``m``, or the first map of the
        chain of merges it was joined to."""
        while self.maps[m]["merged"] is not None:
            m = int(self.maps[m]["merged"]["into"])
        return m

    def layout(self) -> tuple[int, list[tuple[int, int]]]:
        """The current segment as the backend needs it: its first keyframe, and the keyframe
        ranges ``[a, b)`` after it that belong to other segments (maps a merge passed over)."""
        root = self.segment_of(len(self.maps) - 1)
        ends = [int(m["first_keyframe"]) for m in self.maps[1:]]
        excluded = [
            (int(self.maps[m]["first_keyframe"]), ends[m])
            for m in range(root + 1, len(self.maps) - 1)
            if self.segment_of(m) != root and ends[m] > int(self.maps[m]["first_keyframe"])
        ]
        return int(self.maps[root]["first_keyframe"]), excluded

    def merged(self, record: dict[str, Any]) -> None:
        """Record that the current segment was merged: ``record`` holds ``into`` (the first map
        of the segment it joined), ``frame`` and ``keyframe`` (where it happened) and the
        correction; the entry of the segment's first map gets it."""
        self.maps[self.segment_of(len(self.maps) - 1)]["merged"] = dict(record)

    def map_of(self, kf: int) -> int:
        """The map keyframe ``kf`` belongs to."""
        return max(m["map"] for m in self.maps if m["first_keyframe"] <= kf)

    def segment_ates(
        self,
        poses: Sequence[FramePose],
        n_keyframes: int,
        stamped: tuple[np.ndarray, FloatArray, FloatArray],
        truth: tuple[FloatArray, FloatArray],
    ) -> list[dict[str, Any]] | None:
        """The ATE of each segment's frames on their own (Sim(3), evo's pairs): a map kept
        apart has its own frame of reference, which one alignment of the whole trajectory
        mixes in. None for a run with one map.

        Args:
            poses: the system's per-frame records (``index``, ``kf``).
            n_keyframes: keyframes in the store.
            stamped: frame indices (M,), timestamps (M,) and poses (M, 8) of the posed frames.
            truth: ground-truth timestamps (G,) and poses (G, 8).

        Returns:
            per segment: ``segment``, ``maps`` (its maps), ``frames`` (posed) and ``ate_rmse``
            (metres; None when it cannot be computed, e.g. fewer than 3 frames).
        """
        if len(self.maps) < 2:
            return None
        from mslam import evaluate

        idx, ts, T = stamped
        kf_of = {int(p.index): int(p.kf) for p in poses if 0 <= p.kf < n_keyframes}
        seg = np.array([self.segment_of(self.map_of(kf_of[int(i)])) for i in idx], np.int64)
        out = []
        for s in sorted(set(seg.tolist())):
            mine = seg == s
            maps = [int(m["map"]) for m in self.maps if self.segment_of(int(m["map"])) == s]
            try:
                rmse: float | None = evaluate.ate(ts[mine], T[mine], *truth, align="sim3").rmse
            except ValueError:  # too few frames, no spread
                rmse = None
            out.append({"segment": s, "maps": maps, "frames": int(mine.sum()), "ate_rmse": rmse})
        return out

    def report(self, poses: Sequence[FramePose], n_keyframes: int) -> dict[str, Any]:
        """The summary's ``maps`` (each with ``keyframes`` and ``frames_posed`` added) and a
        warning per new map.

        Args:
            poses: the system's per-frame records (``FramePose``: ``index``, ``kf``).
            n_keyframes: keyframes in the store.
        """
        posed: dict[int, int] = {}
        for p in poses:
            if 0 <= p.kf < n_keyframes:
                m = self.map_of(p.kf)
                posed[m] = posed.get(m, 0) + 1
        ends = [m["first_keyframe"] for m in self.maps[1:]] + [n_keyframes]
        maps = [
            {**m, "keyframes": max(0, end - m["first_keyframe"]), "frames_posed": posed.get(i, 0)}
            for i, (m, end) in enumerate(zip(self.maps, ends, strict=True))
        ]
        warnings = [_map_warning(m) for m in self.maps[1:]]
        return {"maps": maps, "warnings": warnings}


def _map_warning(m: Mapping[str, Any]) -> str:
    """The summary's sentence for new map ``m`` (an entry of :attr:`Recovery.maps`)."""
    head = f"a new map (map {m['map']}) was started at frame {m['first_frame']}: {m['reason']}; "
    g = m["merged"]
    if g is not None and g.get("by") == "relocalisation":
        return head + f"it continues map {g['into']} in that map's frame of reference"
    if g is None:
        return head + (
            "it is anchored at the last posed frame's pose and scale, not aligned to the "
            "earlier map (maps are not merged)"
        )
    return head + (
        f"it was merged into map {g['into']} at frame {g['frame']} (keyframe {g['keyframe']} "
        f"connected to keyframe {g['old_keyframe']}; correction: scale {g['scale']:.3g}, "
        f"rotation {g['rot_deg']:.1f} deg, translation {g['translation']:.3g})"
    )
