"""Paper §3.4 — loop-closure candidates by image retrieval: ASMK over local features (docs/upstream.md §7.1–7.2).

A new keyframe queries a database of all earlier keyframes; the best ``k`` with a score above
``min_thresh`` become loop-closure edge candidates (then checked by matching, docs/upstream.md §7.3), and the
keyframe is inserted. Upstream uses ASMK (Tolias et al., "Image search with selective match
kernels", IJCV 2016) with binary signatures over MASt3R's encoder features and a trained 64k-word
codebook. Here the local features are the prior's per-pixel descriptors ``D (H, W, F)`` at the
top-``nfeat`` confidence pixels (:func:`select_features`), and the codebook is trained by k-means
on descriptors available to the run (:func:`train_codebook`; see "Codebook" below).

ASMK, as upstream configures it (binary, no idf, selective kernel α = 3, threshold 0):

1. quantise: each descriptor's ``k`` nearest centroids (5 for a query, 1 for insertion);
2. aggregate per visual word ``w``: ``V_w = Σ_{x → w} (x − c_w)``, binarised to the bits
   ``[V_w > 0]`` (packed into uint32 words, :func:`pack_bits`);
3. word similarity ``sim = 1 − 2·hamming(b_q, b_d)/F``; selective kernel ``σ(sim) = sim³`` if
   ``sim ≥ 0`` else 0;
4. image score ``score(d) = (1/sqrt(n_q)) · Σ_{w in q and d} σ(sim_w) / sqrt(n_d)`` with ``n_q``,
   ``n_d`` the numbers of words of query and database image (idf ≡ 1), so ``score ∈ [0, 1]``
   and an image scores exactly 1 against itself when queried with single assignment.

Codebook: upstream's codebook ships with the checkpoint and cannot be had. The system trains one
at the first keyframe by seeded k-means on a sample of that keyframe's dense descriptors
(``mslam.system.retrieval_features``); because the stand-in descriptors are a fixed function
of local image patches, words learned from one view of a scene quantise every other view of it
consistently. The codebook must be large compared with the words one image hits (a few hundred),
otherwise every image shares every word and unrelated places score like revisits; docs/
evaluation.md gives the measured scores.

Public names, in reading order:
    RetrievalConfig, pool_cell, select_features, train_codebook, quantize, pack_bits, hamming,
    aggregate, asmk_kernel (the database over keyframes is ``mslam_ref.retrieval_database``)

Upstream: mast3r_slam/retrieval_database.py (RetrievalDatabase.update, quantize_custom,
prep_features); asmk (asmk_method.py, functional.py: aggregate, binarize, asmk_kernel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mslam_ref.conventions import FloatArray, IntArray, U32Array, as_float_array

__all__ = [
    "RetrievalConfig",
    "aggregate",
    "asmk_kernel",
    "hamming",
    "pack_bits",
    "pool_cell",
    "quantize",
    "select_features",
    "train_codebook",
]


@dataclass(frozen=True)
class RetrievalConfig:
    """Retrieval settings; names follow upstream's config (``retrieval.*``) and asmk's params.

    Attributes:
        k: candidates returned per query (``retrieval.k``).
        min_thresh: a candidate needs ``score > min_thresh`` (``retrieval.min_thresh``).
        nfeat: local features kept per keyframe (upstream's code default 300).
        query_multiple_assignment: nearest words per query descriptor (asmk ``query``: 5).
        build_multiple_assignment: nearest words per inserted descriptor (asmk ``build``: 1).
        similarity_threshold: selective-kernel threshold on ``sim`` (asmk: 0.0).
        alpha: selective-kernel exponent (asmk: 3.0).
        codebook_size: visual words trained at the first keyframe (see "Codebook" above).
        codebook_samples: descriptors sampled from the first keyframe to train them.
        seed: seed of that sample and of k-means.
    """

    k: int = 3
    min_thresh: float = 5e-3
    nfeat: int = 300
    query_multiple_assignment: int = 5
    build_multiple_assignment: int = 1
    similarity_threshold: float = 0.0
    alpha: float = 3.0
    codebook_size: int = 64
    codebook_samples: int = 4096
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.k, self.nfeat, self.codebook_size, self.codebook_samples) < 1:
            raise ValueError("k, nfeat, codebook_size, codebook_samples: must be >= 1")
        if self.query_multiple_assignment < 1 or self.build_multiple_assignment < 1:
            raise ValueError("query/build_multiple_assignment: must be >= 1")
        if not self.alpha > 0:
            raise ValueError(f"alpha: must be > 0, got {self.alpha}")


#: Number of encoder tokens of MASt3R at 512x384 (16x16-pixel patches): the grid that
#: :func:`select_features` pools descriptors to by default.
TOKEN_GRID_CELLS = 768


def pool_cell(H: int, W: int) -> int:
    """Side of the square pooling cell that gives about ``TOKEN_GRID_CELLS`` cells for HxW.

    ``max(1, round(sqrt(H W / 768)))``: 16 at 512x384 (MASt3R's patch size), 5 at 160x120,
    3 at 96x72.
    """
    return max(1, round(float(np.sqrt(H * W / TOKEN_GRID_CELLS))))


def select_features(
    D: npt.ArrayLike, C: npt.ArrayLike, nfeat: int = 300, cell: int | None = None
) -> FloatArray:
    """The local features of one keyframe: pooled descriptors at the ``nfeat`` most confident cells.

    Upstream: retrieval_database.py::prep_features keeps the top-``nfeat`` encoder tokens (one per
    16x16 patch) by attention (``how_select_local``). The stand-in pools the per-pixel
    descriptors to the same kind of grid: ``D`` is averaged over ``cell x cell`` blocks and
    re-normalised, ``C`` averaged, and the cells are ranked by pooled confidence. Pooling
    matters: single-pixel descriptors at the most confident (highest-contrast) pixels sit on
    texture edges, where they change fastest with the viewpoint, and a revisited place then
    no longer ranks first (docs/evaluation.md).

    Args:
        D: (H, W, F) descriptors.
        C: (H, W) confidence (descriptor confidence Q or pointmap confidence C).
        nfeat: number of features; fewer when there are fewer cells.
        cell: pooling cell side in pixels; None = :func:`pool_cell` (about 768 cells), 1 = no
            pooling. Rows/columns beyond a whole number of cells are dropped.

    Returns:
        (min(nfeat, cells), F) unit descriptors, most confident first (ties by cell index).
    """
    D = as_float_array(D, "D")
    C = as_float_array(C, "C")
    if D.ndim != 3 or C.shape != D.shape[:2]:
        raise ValueError(f"D, C: expected (H, W, F) and (H, W), got {D.shape} and {C.shape}")
    if nfeat < 1:
        raise ValueError(f"nfeat: must be >= 1, got {nfeat}")
    H, W, F = D.shape
    s = pool_cell(H, W) if cell is None else int(cell)
    if not 1 <= s <= min(H, W):
        raise ValueError(f"cell: must be in [1, {min(H, W)}], got {cell}")
    h, w = H // s, W // s
    Dp = D[: h * s, : w * s].reshape(h, s, w, s, F).mean(axis=(1, 3)).reshape(-1, F)
    Cp = C[: h * s, : w * s].reshape(h, s, w, s).mean(axis=(1, 3)).ravel()
    Dp = Dp / np.maximum(np.linalg.norm(Dp, axis=1, keepdims=True), 1e-12)
    order = np.argsort(-Cp, kind="stable")[:nfeat]
    return Dp[order]


def _sq_dists(X: FloatArray, Cb: FloatArray) -> FloatArray:
    """(n, W) squared distances ``‖x‖² + ‖c‖² − 2 x·c`` (upstream quantize_custom), clamped >= 0."""
    d2 = np.sum(X * X, 1)[:, None] + np.sum(Cb * Cb, 1)[None, :] - 2.0 * X @ Cb.T
    return np.maximum(d2, 0.0)


def train_codebook(
    descriptors: npt.ArrayLike, n_clusters: int, seed: int = 0, iters: int = 30
) -> FloatArray:
    """Visual words by k-means (k-means++ seeding, Lloyd iterations), deterministic by ``seed``.

    Upstream: the trained ``*_retrieval_codebook.pkl`` (unavailable; see the module docstring).

    Empty clusters are re-seeded at the point farthest from its centroid. Iteration stops when
    the assignment no longer changes or after ``iters`` rounds.

    Args:
        descriptors: (n, F) training descriptors, n >= n_clusters.
        n_clusters: number of words W.
        seed: seed of the k-means++ draws.
        iters: maximum Lloyd iterations.

    Returns:
        (W, F) centroids.
    """
    X = as_float_array(descriptors, "descriptors")
    if X.ndim != 2 or len(X) == 0:
        raise ValueError(f"descriptors: expected a non-empty (n, F) array, got {X.shape}")
    if not 1 <= n_clusters <= len(X):
        raise ValueError(f"n_clusters: must be in [1, {len(X)}], got {n_clusters}")
    rng = np.random.default_rng(seed)
    centres = [X[rng.integers(len(X))]]
    d2 = np.sum((X - centres[0]) ** 2, 1)
    for _ in range(1, n_clusters):
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(len(X), 1.0 / len(X))
        c = X[rng.choice(len(X), p=p)]
        centres.append(c)
        d2 = np.minimum(d2, np.sum((X - c) ** 2, 1))
    Cb = np.array(centres)
    assign = np.full(len(X), -1)
    for _ in range(iters):
        dist = _sq_dists(X, Cb)
        new = np.argmin(dist, 1)
        if np.array_equal(new, assign):
            break
        assign = new
        counts = np.bincount(assign, minlength=n_clusters)
        sums = np.zeros_like(Cb)
        np.add.at(sums, assign, X)
        full = counts > 0
        Cb[full] = sums[full] / counts[full, None]
        far = np.argsort(-dist[np.arange(len(X)), assign], kind="stable")
        for j, w in enumerate(np.flatnonzero(~full)):
            Cb[w] = X[far[j]]
    return Cb


def quantize(codebook: npt.ArrayLike, X: npt.ArrayLike, k: int) -> IntArray:
    """The ``k`` nearest visual words of each descriptor, nearest first.

    Upstream: retrieval_database.py::quantize_custom (dense distance matrix + topk).

    Args:
        codebook: (W, F) centroids.
        X: (n, F) descriptors.
        k: words per descriptor (clamped to W).

    Returns:
        (n, min(k, W)) int64 word ids (ties by word id).
    """
    Cb = as_float_array(codebook, "codebook")
    X = as_float_array(X, "X")
    if X.ndim != 2 or Cb.ndim != 2 or X.shape[1] != Cb.shape[1]:
        raise ValueError(f"X: expected (n, {Cb.shape[-1]}) descriptors, got {X.shape}")
    k = min(int(k), len(Cb))
    return np.argsort(_sq_dists(X, Cb), axis=1, kind="stable")[:, :k].astype(np.int64)


def pack_bits(B: npt.ArrayLike) -> U32Array:
    """Pack boolean rows into uint32 words: bit ``j`` of a row is bit ``j % 32`` of word ``j // 32``.

    Args:
        B: (m, F) booleans.

    Returns:
        (m, ceil(F / 32)) uint32 (unused high bits are 0).
    """
    B = np.asarray(B, dtype=bool)
    if B.ndim != 2:
        raise ValueError(f"B: expected (m, F) booleans, got {B.shape}")
    n_words = -(-B.shape[1] // 32)
    padded = np.zeros((B.shape[0], 32 * n_words), dtype=bool)
    padded[:, : B.shape[1]] = B
    by = np.packbits(padded, axis=1, bitorder="little")  # (m, 4 * n_words) bytes
    return np.ascontiguousarray(by).view("<u4").astype(np.uint32).reshape(B.shape[0], n_words)


def hamming(a: U32Array, b: U32Array) -> IntArray:
    """Hamming distance between packed bit rows (broadcasting over leading axes): (...,)."""
    return np.bitwise_count(np.bitwise_xor(a, b)).sum(axis=-1).astype(np.int64)


def aggregate(
    codebook: npt.ArrayLike, X: npt.ArrayLike, words: npt.ArrayLike
) -> tuple[IntArray, U32Array]:
    """Binary ASMK signatures of one image: per word, the sign bits of the summed residuals.

    Upstream: asmk functional.py (aggregate residuals per word, binarize ``> 0``, packed).

    ``V_w = Σ_{(x, w) assigned} (x − c_w)``; every assignment of ``words`` counts (multiple
    assignment adds a descriptor's residual to each of its words).

    Args:
        codebook: (W, F) centroids.
        X: (n, F) descriptors.
        words: (n, a) word ids per descriptor (from :func:`quantize`).

    Returns:
        word ids (m,) sorted ascending and their signatures (m, ceil(F / 32)) uint32.
    """
    Cb = as_float_array(codebook, "codebook")
    X = as_float_array(X, "X")
    words = np.asarray(words, dtype=np.int64)
    if words.ndim != 2 or len(words) != len(X):
        raise ValueError(f"words: expected ({len(X)}, a), got {words.shape}")
    flat_w = words.ravel()
    residuals = np.repeat(X, words.shape[1], axis=0) - Cb[flat_w]
    uniq, inv = np.unique(flat_w, return_inverse=True)
    V = np.zeros((len(uniq), Cb.shape[1]))
    np.add.at(V, inv, residuals)
    return uniq.astype(np.int64), pack_bits(V > 0)


def asmk_kernel(sim: FloatArray, cfg: RetrievalConfig) -> FloatArray:
    """Selective match kernel ``σ(sim) = max(sim, 0)^α`` where ``sim >= threshold``, else 0."""
    return np.where(sim >= cfg.similarity_threshold, np.maximum(sim, 0.0) ** cfg.alpha, 0.0)
