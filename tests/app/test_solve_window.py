"""The windowed backend solve (``local_opt.window_size``, ``FactorGraph.window``).

A long sequence's map grows without bound; a solve that moves only the recent keyframes and
the new keyframe's loop partners, against their fixed neighbours, keeps each solve's cost
bounded. These tests check which keyframes move, which stay fixed, that the blocks follow the
window, and that a window covering the map is the whole-graph solve bit for bit.
"""

from __future__ import annotations

import numpy as np

from mslam.config import load_config
from mslam.kernels import load_kernels
from mslam.system import open_source, run_slam
from mslam.system.edges import Edge
from mslam.system.graph import FactorGraph

LOOP = "synthetic:loop:24:64x48"
N_PIX = 6


def _edge(i: int, j: int, kind: str = "retrieval") -> Edge:
    idx = np.arange(N_PIX, dtype=np.int64)
    ok = np.ones(N_PIX, bool)
    q = np.full(N_PIX, 2.0)
    return Edge(i, j, idx, idx[::-1].copy(), ok, ok, q, q, 1.0, kind)


def _chain_with_loop(n: int, loop: tuple[int, int]) -> FactorGraph:
    """Consecutive edges 0-1-...-(n-1) and one loop-closure edge."""
    graph = FactorGraph(edges=[_edge(k - 1, k, "consecutive") for k in range(1, n)])
    graph.edges.append(_edge(*loop))
    return graph


def test_window_covering_the_map_is_the_whole_graph():
    graph = _chain_with_loop(6, (1, 5))
    for size in (6, 7, 1e6):
        win = graph.window(6, size)
        assert not win.windowed and win.pin == 1
        assert np.array_equal(win.keyframes, np.arange(6))


def test_window_moves_recent_keyframes_and_loop_partners_against_fixed_neighbours():
    graph = _chain_with_loop(10, (2, 9))
    win = graph.window(10, 3)
    assert win.windowed
    fixed, moved = list(win.keyframes[: win.pin]), list(win.keyframes[win.pin :])
    # recent 7, 8, 9 and the newest keyframe's loop partner 2 move; their other neighbours
    # (1 and 3 around the partner, 6 before the window) hold them.
    assert moved == [2, 7, 8, 9]
    assert fixed == [1, 3, 6]


def test_window_of_a_later_map_never_reaches_an_earlier_one():
    graph = _chain_with_loop(10, (6, 9))
    graph.edges = [e for e in graph.edges if not (e.i == 4 and e.j == 5)]  # map 2 starts at 5
    win = graph.window(10, 2, first=5)
    assert win.windowed and min(win.keyframes) >= 5
    assert list(win.keyframes[: win.pin]) == [5, 7]


def test_blocks_follow_the_window():
    graph = _chain_with_loop(10, (2, 9))
    win = graph.window(10, 3)
    b = graph.two_way_blocks(None, 0, win)
    pos = {int(k): n for n, k in enumerate(win.keyframes)}
    kept = {(e.i, e.j) for e in graph.edges if e.i in pos and e.j in pos}
    kept = {(i, j) for i, j in kept if max(pos[i], pos[j]) >= win.pin}
    # every edge touching a moved keyframe, none between two fixed ones, in window positions
    assert len(b.ii) == 2 * len(kept)
    E = len(kept)
    pairs = {(int(win.keyframes[i]), int(win.keyframes[j])) for i, j in zip(b.ii[:E], b.jj[:E])}
    assert pairs == kept
    assert b.ii.max() < len(win.keyframes) and np.all(np.maximum(b.ii, b.jj) >= win.pin)


def _system(window: float):
    import mslam_fast

    mslam_fast.init("cpu", "f64")
    cfg = load_config(None, [f"local_opt.window_size={window}"])
    src = open_source(LOOP, cfg)
    system, _ = run_slam(src, cfg, load_kernels("fast"))
    return system


def test_a_window_as_large_as_the_map_gives_the_same_run():
    whole = _system(1e6)
    K = len(whole.keyframes)
    same = _system(K)
    assert np.array_equal(whole.keyframes.poses(), same.keyframes.poses())


def test_a_windowed_solve_keeps_the_keyframes_outside_it():
    system = _system(3)
    backend = system.backend
    K = len(system.keyframes)
    win = backend.graph.window(K, 3, backend.map_start)
    assert win.windowed and len(win.keyframes) < K
    before = system.keyframes.poses()
    record = backend.solve()
    assert record is not None
    after = system.keyframes.poses()
    outside = np.setdiff1d(np.arange(K), win.keyframes[win.pin :])
    assert np.array_equal(after[outside], before[outside])
    assert np.all(np.isfinite(after))
