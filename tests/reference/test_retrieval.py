"""ASMK-style retrieval (mslam_ref.retrieval): bit packing, aggregation, scoring, the database."""

from __future__ import annotations

import importlib.util

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from numpy.lib.stride_tricks import sliding_window_view
from tolerances import F64_COPY, SCORE_SYMMETRY

from mslam_ref import retrieval as R
from mslam_ref.retrieval_database import RetrievalDatabase

F = 24


# ---- building blocks against naive implementations ----


@given(seed=st.integers(0, 10_000), m=st.integers(0, 6), f=st.integers(1, 70))
def test_pack_bits_matches_naive(seed, m, f) -> None:
    B = np.random.default_rng(seed).random((m, f)) < 0.5
    packed = R.pack_bits(B)
    assert packed.dtype == np.uint32 and packed.shape == (m, -(-f // 32))
    naive = np.zeros_like(packed)
    for i in range(m):
        for j in range(f):
            if B[i, j]:
                naive[i, j // 32] |= np.uint32(1 << (j % 32))
    np.testing.assert_array_equal(packed, naive)


@given(seed=st.integers(0, 10_000), f=st.integers(1, 70))
def test_hamming_matches_naive(seed, f) -> None:
    rng = np.random.default_rng(seed)
    A, B = rng.random((5, f)) < 0.5, rng.random((5, f)) < 0.5
    got = R.hamming(R.pack_bits(A), R.pack_bits(B))
    np.testing.assert_array_equal(got, np.sum(A != B, axis=1))


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@given(seed=st.integers(0, 10_000), a=st.integers(1, 5))
def test_quantize_and_aggregate_match_naive(seed, a) -> None:
    rng = np.random.default_rng(seed)
    cb = _unit(rng.normal(size=(12, F)))
    X = _unit(rng.normal(size=(30, F)))
    words = R.quantize(cb, X, a)
    d = np.linalg.norm(X[:, None] - cb[None], axis=-1)
    np.testing.assert_array_equal(words, np.argsort(d, axis=1, kind="stable")[:, :a])
    w_ids, bits = R.aggregate(cb, X, words)
    V = {}
    for i in range(len(X)):
        for w in words[i]:
            V[int(w)] = V.get(int(w), 0.0) + (X[i] - cb[w])
    assert w_ids.tolist() == sorted(V)
    np.testing.assert_array_equal(bits, R.pack_bits(np.array([V[w] > 0 for w in sorted(V)])))


def test_train_codebook_deterministic_and_finds_clusters() -> None:
    rng = np.random.default_rng(0)
    centres = rng.normal(0, 5, (8, F))
    X = np.concatenate([c + rng.normal(0, 0.1, (50, F)) for c in centres])
    cb1 = R.train_codebook(X, 8, seed=3)
    np.testing.assert_array_equal(cb1, R.train_codebook(X, 8, seed=3))
    err = np.linalg.norm(cb1[:, None] - centres[None], axis=-1).min(axis=0)
    assert err.max() < 0.1
    with pytest.raises(ValueError, match="n_clusters"):
        R.train_codebook(X[:5], 8)


def test_select_features_pools_to_token_grid_and_ranks_by_confidence() -> None:
    rng = np.random.default_rng(0)
    D = _unit(rng.normal(size=(12, 16, F)))
    C = rng.uniform(1, 2, (12, 16))
    f1 = R.select_features(D, C, nfeat=5, cell=1)
    order = np.argsort(-C.ravel(), kind="stable")[:5]
    np.testing.assert_allclose(f1, D.reshape(-1, F)[order], rtol=0, atol=F64_COPY)
    f4 = R.select_features(D, C, nfeat=100, cell=4)  # 3 x 4 cells
    assert f4.shape == (12, F)
    np.testing.assert_allclose(np.linalg.norm(f4, axis=1), 1.0)
    best = np.argmax(C.reshape(3, 4, 4, 4).mean(axis=(1, 3)))
    pooled = _unit(D.reshape(3, 4, 4, 4, F).mean(axis=(1, 3)).reshape(-1, F))
    np.testing.assert_allclose(f4[0], pooled[best])
    assert R.pool_cell(384, 512) == 16 and R.pool_cell(72, 96) == 3
    with pytest.raises(ValueError, match="D, C"):
        R.select_features(D, C[:5], 5)


# ---- scores and the database protocol ----


def _place(rng, anchors: np.ndarray, spread: float, n: int = 400) -> np.ndarray:
    """The "landmarks" of a place: unit descriptors scattered around the place's anchors."""
    pick = rng.integers(len(anchors), size=n)
    return _unit(anchors[pick] + spread * rng.normal(size=(n, F)))


def _view(rng, landmarks: np.ndarray, n: int = 300) -> np.ndarray:
    """One view of a place: most of its landmarks, re-observed with descriptor noise."""
    take = rng.choice(len(landmarks), n, replace=False)
    return _unit(landmarks[take] + rng.normal(0, 0.03, (n, F)))


@pytest.fixture(scope="module")
def places():
    """Six places (two random anchor directions each) and a 128-word codebook over all."""
    rng = np.random.default_rng(7)
    lms = [_place(rng, _unit(rng.normal(size=(2, F))), 0.25) for _ in range(6)]
    return lms, R.train_codebook(np.concatenate(lms), 128, seed=0)


def test_self_score_is_one_with_single_assignment_and_scores_in_range(places) -> None:
    lms, cb = places
    rng = np.random.default_rng(1)
    feats = [_view(rng, lm) for lm in lms]
    db1 = RetrievalDatabase(cb, R.RetrievalConfig(query_multiple_assignment=1))
    db5 = RetrievalDatabase(cb)
    for f in feats:
        db1.insert(f)
        db5.insert(f)
    for i, f in enumerate(feats):
        s1, s5 = db1.scores(f), db5.scores(f)
        assert s1[i] == pytest.approx(1.0)
        assert np.all((s1 >= 0) & (s1 <= 1 + 1e-12)) and np.all((s5 >= 0) & (s5 <= 1 + 1e-12))
        assert np.argmax(s5) == i


def test_revisit_ranks_first_and_scores_are_symmetric_ish(places) -> None:
    lms, cb = places
    rng = np.random.default_rng(2)
    db = RetrievalDatabase(cb)
    for lm in lms:
        db.update(_view(rng, lm))
    S = np.array([db.scores(_view(rng, lm)) for lm in lms])  # new views of each place
    assert np.all(np.argmax(S, axis=1) == np.arange(6))
    off = S[~np.eye(6, dtype=bool)]
    assert np.diag(S).min() > 5e-3 and np.diag(S).mean() > 5 * off.mean()
    # swapping query and database image changes a score only a little (MA 5 vs 1 breaks symmetry)
    np.testing.assert_allclose(S, S.T, atol=SCORE_SYMMETRY * np.diag(S).min())


def test_unrelated_places_score_below_threshold() -> None:
    """Places whose descriptors fall in different visual words share no word: score 0."""
    rng = np.random.default_rng(4)
    axes = np.eye(F)
    lms = [_place(rng, axes[[3 * p, 3 * p + 1, 3 * p + 2]], 0.08) for p in range(6)]
    cb = R.train_codebook(np.concatenate(lms), 96, seed=0)
    db = RetrievalDatabase(cb)
    for lm in lms[:5]:
        db.update(_view(rng, lm))
    s = db.scores(_view(rng, lms[5]))  # a place never inserted
    assert s.max() < 5e-3
    assert db.update(_view(rng, lms[5]), k=3, min_thresh=5e-3) == []
    assert db.query(_view(rng, lms[2]), k=3, min_thresh=0.0)[0][0] == 2


def test_update_protocol() -> None:
    rng = np.random.default_rng(3)
    cb = _unit(rng.normal(size=(16, F)))
    db = RetrievalDatabase(cb, R.RetrievalConfig(query_multiple_assignment=1))
    f = [_unit(rng.normal(size=(50, F))) for _ in range(5)]
    assert db.update(f[0]) == [] and db.kf_counter == 1 and len(db) == 1
    assert db.update(f[1], add_after_query=False, k=3, min_thresh=-1.0) == [0]
    assert db.kf_counter == 1
    for x in f[1:]:
        db.update(x)
    assert db.kf_counter == 5
    res = db.query(f[2], k=10, min_thresh=-1.0)
    assert len(res) == 5 and res[0][0] == 2
    assert [s for _, s in res] == sorted((s for _, s in res), reverse=True)
    assert len(db.query(f[2], k=2, min_thresh=-1.0)) == 2
    assert db.update(f[2], add_after_query=False, k=3, min_thresh=2.0) == []
    assert RetrievalDatabase(cb).query(f[0]) == []
    with pytest.raises(ValueError, match="features"):
        db.query(np.zeros((3, F + 1)))
    with pytest.raises(ValueError, match="features"):
        db.update(np.zeros((0, F)))


# ---- images: patch descriptors of textures, and the synthetic room ----


_P = np.random.default_rng(24).standard_normal((75, F)) / np.sqrt(75)


def _texture(seed: int, size: int = 140) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3))
    for sig, amp in ((8.0, 1.0), (3.0, 0.6), (1.2, 0.3)):
        img += amp * sig * cv2.GaussianBlur(rng.standard_normal((size, size, 3)), (0, 0), sig)
    return img


def _patch_descriptors(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our own 5x5 colour-patch descriptors (D (H,W,24) unit, contrast confidence (H,W))."""
    pad = np.pad(img, ((2, 2), (2, 2), (0, 0)), mode="edge")
    z = sliding_window_view(pad, (5, 5), axis=(0, 1)).reshape(*img.shape[:2], -1)
    z = z - z.mean(-1, keepdims=True)
    sd = z.std(-1, keepdims=True)
    return _unit((z / (sd + 0.02)) @ _P), 1.0 + sd[..., 0]


def test_revisited_texture_view_ranks_first() -> None:
    rng = np.random.default_rng(0)
    tex = [_texture(s) for s in range(5)]

    def view(t, y, x):
        return _patch_descriptors(t[y : y + 48, x : x + 64] + rng.normal(0, 0.05, (48, 64, 3)))

    D0, _ = view(tex[0], 10, 10)
    cb = R.train_codebook(D0.reshape(-1, F)[::2], 64, seed=0)
    db = RetrievalDatabase(cb)
    for t in tex:
        db.update(R.select_features(*view(t, 40, 40)))
    for p, t in enumerate(tex):
        s = db.scores(R.select_features(*view(t, 44, 36)))  # a shifted, re-noised revisit
        assert np.argmax(s) == p and s[p] > 5e-3


@pytest.mark.skipif(
    importlib.util.find_spec("mslam.priors.synthetic") is None,
    reason="mslam.priors.synthetic not available",
)
def test_synthetic_room_revisit_is_retrieved() -> None:
    """The ``detour`` path retraces its first arc: each retraced keyframe retrieves a keyframe
    of the same place (view distance < 0.5 m) as its best non-recent candidate."""
    from mslam.datasets.synthetic import make_sequence
    from mslam.priors.synthetic import SyntheticPrior
    from mslam_ref import sim3

    n = 40
    seq = make_sequence("detour", n_frames=n, width=96, height=72, seed=0)
    prior = SyntheticPrior(seq)
    kf = list(range(0, n, 3))
    feats, first = [], None
    for i in kf:
        p = prior.pair(seq[i], seq[i])
        if first is None:
            first = p.D_ii.reshape(-1, F)
        feats.append(R.select_features(p.D_ii, p.Q_ii))
    take = np.random.default_rng(0).choice(len(first), 4096, replace=False)
    db = RetrievalDatabase(R.train_codebook(first[np.sort(take)], 256, seed=0))
    T = seq.T_WC

    def view_dist(i: int, j: int) -> float:
        p = sim3.act(T[[i, j]], np.array([0.0, 0.0, 1.5]))
        return float(np.linalg.norm(p[0] - p[1]) + np.linalg.norm(T[i, :3] - T[j, :3]))

    checked = 0
    for k, i in enumerate(kf):
        s = db.scores(feats[k]) if k else np.zeros(0)
        db.insert(feats[k])
        old = s[: max(k - 2, 0)]  # skip the two most recent keyframes
        d = np.array([view_dist(i, kf[j]) for j in range(len(old))])
        if len(old) and d.min() < 0.5:  # a revisit exists among the old keyframes
            assert d[np.argmax(old)] < 0.5 and old.max() > 5e-3
            checked += 1
    assert checked >= 3
