"""Relocalisation into an earlier map (mslam.system.reloc, ``rejoin``).

``synthetic:detour`` leaves the mapped arc for a place it never saw, then jumps back and
retraces the arc. With ``recovery.max_lost_frames`` small, a second map starts in the detour;
at the return, tracking against that map fails, and relocalisation, finding nothing in the
current map, tries the first map's keyframes: the return frame is relocalised there, a third
map entry records that the run continues the first map (merged by relocalisation, no
correction), and the retraced frames land where the first map's frame of reference puts them.
With ``recovery.merge_maps=0`` the maps stay apart and the return frames stay lost until
another new map starts. The background backend (``single_thread: False``) rejoins the same way.
"""

from __future__ import annotations

import numpy as np
import pytest
from tolerances import REJOINED_FRAME_M

from mslam.config import load_config
from mslam.evaluate import umeyama
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.outputs import evaluate_run, summary_dict
from mslam.system.recovery import Recovery
from mslam_ref.synthetic import detour_indices

DETOUR = "synthetic:detour:48:96x72"
MAX_LOST = 4  # recovery.max_lost_frames: a second map starts inside the detour


def _run(*overrides: str):
    cfg = load_config(None, [f"recovery.max_lost_frames={MAX_LOST}", *overrides])
    src = open_source(DETOUR, cfg)
    system, meta = run_slam(src, cfg, load_kernels("fast"))
    return system, src, summary_dict(system, meta, evaluate_run(system, src.sequence))


@pytest.fixture(scope="module")
def rejoined():
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    return _run()


def test_the_return_frame_relocalises_into_the_first_map(rejoined) -> None:
    system, src, s = rejoined
    n = len(src.sequence)
    j1, j2 = detour_indices(n)
    assert len(s["maps"]) == 3, s["maps"]
    detour, back = s["maps"][1], s["maps"][2]
    assert detour["merged"] is None and j1 < detour["first_frame"] < j2
    merged = back["merged"]
    assert merged is not None and merged["into"] == 0 and merged["by"] == "relocalisation"
    assert merged["old_keyframe"] < detour["first_keyframe"]
    assert j2 <= back["first_frame"] <= j2 + 2 and s["relocalised_at"] == [back["first_frame"]]
    assert any("continues map 0" in w for w in s["warnings"])
    # The backend's map is the first one again, without the detour's keyframes.
    assert system.backend.map_start == 0
    assert not system.backend.in_map(detour["first_keyframe"])


def test_the_retraced_frames_land_in_the_first_maps_frame(rejoined) -> None:
    system, src, s = rejoined
    j1 = detour_indices(len(src.sequence))[0]
    idx, _, T = system.frame_poses()
    gt = np.stack([src.sequence.T_WC[i, :3] for i in idx])
    first = idx < j1
    R, t, scale = umeyama(T[first, :3], gt[first])
    err = np.linalg.norm(scale * T[:, :3] @ R.T + t - gt, axis=1)
    back = idx >= s["maps"][2]["first_frame"]
    assert back.sum() == len(src.sequence) - s["maps"][2]["first_frame"]  # every one posed
    assert np.max(err[back]) < REJOINED_FRAME_M, err[back]
    # The summary's ATE per segment: the first map and the one continuing it, aligned on their
    # own, leave the detour's map (its own frame of reference) out of their error.
    first, detour = s["ate_by_map"]
    assert first["maps"] == [0, 2] and detour["maps"] == [1]
    assert first["frames"] + detour["frames"] == s["frames_with_pose"]
    assert first["ate_rmse"] < REJOINED_FRAME_M < s["ate_rmse"]


def test_without_merging_the_return_stays_lost_until_a_new_map() -> None:
    _, src, s = _run("recovery.merge_maps=0")
    j2 = detour_indices(len(src.sequence))[1]
    assert all(m["merged"] is None for m in s["maps"]), s["maps"]
    assert [seg["maps"] for seg in s["ate_by_map"]] == [[0], [1], [2]]
    assert not any(r >= j2 for r in s["relocalised_at"])
    assert any(a <= j2 <= b and b - a + 1 >= MAX_LOST for a, b in s["lost_spans"])


def test_a_rejoining_map_is_laid_out_with_the_map_it_continues() -> None:
    rec = Recovery()
    rec.new_map(30, 4, "lost")  # map 1: keyframes 4-6, never merged
    rec.rejoined(40, 7, 2)  # map 2 continues map 0
    assert rec.segment_of(2) == 0 and rec.maps[2]["merged"]["old_keyframe"] == 2
    assert rec.layout() == (0, [(4, 7)])
    assert "continues map 0" in rec.report([], 9)["warnings"][1]


def test_the_background_backend_rejoins_too() -> None:
    _, src, s = _run("single_thread=false")
    j2 = detour_indices(len(src.sequence))[1]
    back = s["maps"][-1]
    assert back["merged"] is not None and back["merged"]["by"] == "relocalisation", s["maps"]
    assert back["merged"]["into"] == 0 and j2 <= back["first_frame"] <= j2 + 2
