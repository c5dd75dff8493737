"""Map merging (mslam.system.merge): a new map joins the earlier one when the camera returns.

* The corrections: a connection's Sim(3) puts the new keyframe where the old map says it is;
  connections whose corrections disagree, or a lone one, merge nothing.
* A synthetic loop with a blind stretch: the second map starts after it; when the camera comes
  back to the loop's start the maps are merged, and the second map's keyframes land where the
  first map's frame of reference puts them (truth under the first map's alignment). Cut off
  before the return, the second map sees only places the first never saw and stays apart.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from blind_prior import BlindPrior
from tolerances import MERGED_KEYFRAME_M, MERGED_MAP_MEDIAN_M, SIM3_FIT

from mslam.config import load_config
from mslam.evaluate import umeyama
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.keyframes import Keyframe, KeyframeStore
from mslam.system.merge import Connection, MapMerger, MergeConfig, agree, correction
from mslam.system.outputs import evaluate_run, summary_dict
from mslam.system.recovery import Recovery
from mslam_ref import sim3

LOOP = "synthetic:loop:56:96x72"
BLIND = range(16, 20)  # frames the blind prior sees nothing in: a new map starts after them
MAX_LOST = 4  # recovery.max_lost_frames
BEFORE_RETURN = 40  # frames of the loop that never come back to its start
#: A longer blind stretch: maps started inside it hold one blank keyframe each.
LOOP_LONG, BLIND_LONG = "synthetic:loop:64:96x72", range(12, 24)


def _run(max_frames: int | None = None, loop: str = LOOP, blind: range = BLIND, overrides=()):
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    cfg = load_config(None, [f"recovery.max_lost_frames={MAX_LOST}", *overrides])
    src = open_source(loop, cfg, max_frames=max_frames)
    src.prior = BlindPrior(src.prior, blind)
    system, meta = run_slam(src, cfg, load_kernels("fast"))
    return system, summary_dict(system, meta, evaluate_run(system, src.sequence))


def _errors_under_first_map(system, first_new: int) -> np.ndarray:
    """(K,) keyframe position errors (m) against the truth, under the Sim(3) that aligns the
    first map's keyframes (0 .. first_new - 1) to their true positions."""
    est = np.stack([kf.T_WC[:3] for kf in system.keyframes])
    gt = np.stack([kf.frame.T_WC[:3] for kf in system.keyframes])
    R, t, s = umeyama(est[:first_new], gt[:first_new])
    return np.linalg.norm(s * est @ R.T + t - gt, axis=1)


@pytest.fixture(scope="module")
def returning():
    return _run()


def test_the_camera_returning_merges_the_second_map_onto_the_first(returning) -> None:
    system, s = returning
    assert len(s["maps"]) == 2, s["maps"]
    new = s["maps"][1]
    merged = new["merged"]
    assert merged is not None and merged["into"] == 0, s["maps"]
    assert merged["connections"] >= MergeConfig().min_support
    assert any(f"it was merged into map 0 at frame {merged['frame']}" in w for w in s["warnings"])
    assert not any("maps are not merged" in w for w in s["warnings"])
    # One map for the backend: merge edges join the maps.
    first_new = new["first_keyframe"]
    joins = [e for e in system.graph.edges if (e.i < first_new) != (e.j < first_new)]
    assert joins and all(e.kind == "merge" for e in joins)
    assert system.backend.map_start == 0
    err = _errors_under_first_map(system, first_new)
    assert err[merged["keyframe"]] < MERGED_KEYFRAME_M, err
    assert np.median(err[first_new:]) < MERGED_MAP_MEDIAN_M, err


def test_the_background_backend_merges_too() -> None:
    system, s = _run(overrides=["single_thread=false"])
    merged = s["maps"][1]["merged"]
    assert merged is not None and merged["into"] == 0, s["maps"]
    err = _errors_under_first_map(system, s["maps"][1]["first_keyframe"])
    assert err[merged["keyframe"]] < MERGED_KEYFRAME_M, err


def test_a_second_map_in_places_the_first_never_saw_stays_apart() -> None:
    system, s = _run(BEFORE_RETURN)
    assert len(s["maps"]) == 2 and s["maps"][1]["merged"] is None, s["maps"]
    # Connections were looked for, and none was verified.
    assert system.merger.checks and not any(c["accepted"] for c in system.merger.checks)
    first_new = s["maps"][1]["first_keyframe"]
    assert all((e.i < first_new) == (e.j < first_new) for e in system.graph.edges)
    assert any("maps are not merged" in w for w in s["warnings"])


def _store(T_WC: list[np.ndarray], depth: float = 2.0) -> KeyframeStore:
    """Keyframes at the given poses whose points lie ``depth`` in front of the camera."""
    store = KeyframeStore()
    for T in T_WC:
        X = np.tile([0.0, 0.0, depth], (12, 1))
        store.append(Keyframe(frame=None, T_WC=T, state=SimpleNamespace(X_canon=X), shape=(3, 4)))
    return store


def _sim3(rng, scale: float = 1.0) -> np.ndarray:
    return sim3.exp(np.concatenate([rng.normal(0, scale, 3), rng.normal(0, 0.5, 3), [0.2]]))


def _connection(store: KeyframeStore, i: int, j: int, T_WCi_true: np.ndarray) -> Connection:
    """A connection whose fit is the true relative pose of keyframe i (true pose given) and j."""
    T_CiCj = sim3.mul(sim3.inv(T_WCi_true), store[j].T_WC)
    return Connection(SimpleNamespace(i=i, j=j), T_CiCj, inlier_frac=0.9, matches=1000)


def test_a_correction_puts_the_new_keyframe_where_the_old_map_says() -> None:
    rng = np.random.default_rng(0)
    S_true = _sim3(rng)
    T_old, T_true = _sim3(rng), _sim3(rng)
    store = _store([T_old, sim3.mul(sim3.inv(S_true), T_true)])  # keyframe 1: the new map's
    c = _connection(store, 1, 0, T_true)
    S = correction(c, store)
    np.testing.assert_allclose(sim3.to_matrix(S), sim3.to_matrix(S_true), atol=SIM3_FIT)
    np.testing.assert_allclose(
        sim3.to_matrix(sim3.mul(S, store[1].T_WC)), sim3.to_matrix(T_true), atol=SIM3_FIT
    )


def test_only_agreeing_connections_merge() -> None:
    rng = np.random.default_rng(1)
    S_true = _sim3(rng, 0.3)
    T_old = [_sim3(rng, 0.3) for _ in range(2)]
    T_true = [sim3.mul(T_old[0], _sim3(rng, 0.1)), sim3.mul(T_old[1], _sim3(rng, 0.1))]
    store = _store([*T_old, *(sim3.mul(sim3.inv(S_true), T) for T in T_true)])
    good = [_connection(store, 2, 0, T_true[0]), _connection(store, 3, 1, T_true[1])]
    # A wrong connection: keyframe 3 claimed 40 degrees away from where it is.
    turned = sim3.mul(T_true[1], sim3.exp(np.array([0, 0, 0, 0, np.radians(40), 0, 0.0])))
    wrong = _connection(store, 3, 0, turned)
    cfg = MergeConfig()
    assert agree(good[0], good[1], store, cfg)
    assert not agree(good[0], wrong, store, cfg) and not agree(good[1], wrong, store, cfg)
    merger = MapMerger(cfg)
    merger.pending = [good[0], wrong]  # a lone connection and a disagreeing one
    assert merger.agreeing(store) is None
    merger.pending = [wrong, *good]
    group = merger.agreeing(store)
    assert group is not None and {id(c) for c in group} == {id(c) for c in good}


def test_merges_record_segments_and_the_maps_passed_over() -> None:
    rec = Recovery()
    rec.new_map(10, 4, "lost")
    rec.new_map(20, 7, "lost")
    rec.new_map(30, 8, "lost")
    assert rec.layout() == (8, [])
    rec.merged({"into": 1, "frame": 35, "keyframe": 9, "old_keyframe": 5, "connections": 2,
                "scale": 1.1, "rot_deg": 3.0, "translation": 0.2})  # fmt: skip
    # Map 3 joined map 1 past map 2, whose keyframe (7) stays out of the current map.
    assert rec.segment_of(3) == 1 and rec.segment_of(2) == 2
    assert rec.layout() == (4, [(7, 8)])
    rec.merged({"into": 0, "frame": 40, "keyframe": 11, "old_keyframe": 2, "connections": 3,
                "scale": 0.9, "rot_deg": 1.0, "translation": 0.1})  # fmt: skip
    assert rec.segment_of(3) == 0 and rec.segment_of(1) == 0 and rec.layout() == (0, [(7, 8)])
    warnings = rec.report([], 12)["warnings"]
    assert "merged into map 0 at frame 40" in warnings[0]
    assert "was started at frame 20" in warnings[1] and "maps are not merged" in warnings[1]
    assert "merged into map 1 at frame 35" in warnings[2]


@pytest.fixture(scope="module")
def passing_over():
    return _run(loop=LOOP_LONG, blind=BLIND_LONG)


def test_a_merge_passes_over_maps_that_saw_nothing(passing_over) -> None:
    system, s = passing_over
    maps = s["maps"]
    assert len(maps) >= 3 and maps[-1]["merged"] is not None, maps
    assert maps[-1]["merged"]["into"] == 0
    between = maps[1:-1]  # maps started inside the blind stretch: one blank keyframe each
    assert all(m["merged"] is None for m in between)
    skipped = {
        k for m in between for k in range(m["first_keyframe"], m["first_keyframe"] + m["keyframes"])
    }
    assert skipped and all(not system.backend.in_map(k) for k in skipped)
    assert not any(e.i in skipped or e.j in skipped for e in system.graph.edges)
    # The keyframe that made the merge is where the first map's frame puts it (the map's far
    # end keeps the drift it had: nothing joins it to the first map there).
    err = _errors_under_first_map(system, maps[1]["first_keyframe"])
    assert err[maps[-1]["merged"]["keyframe"]] < MERGED_KEYFRAME_M, err
