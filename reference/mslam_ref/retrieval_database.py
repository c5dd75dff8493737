"""Paper §3.4 — the retrieval database: ASMK over every keyframe, queried by each new one.

Keyframes are inserted in order (their id is the insertion counter); a new keyframe first
queries the database for its best ``k`` earlier keyframes with a score above ``min_thresh``
(loop-closure candidates), then is inserted. The scoring maths (quantisation, aggregation,
binary signatures, the selective kernel) is in ``mslam_ref.retrieval``; this module keeps the
inverted file.

Public names: RetrievalDatabase.

Upstream: mast3r_slam/retrieval_database.py::RetrievalDatabase (``update``, ``kf_counter``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from mslam_ref.conventions import FloatArray, IntArray, U32Array, as_float_array
from mslam_ref.retrieval import RetrievalConfig, aggregate, asmk_kernel, hamming, quantize

__all__ = ["RetrievalDatabase"]


class RetrievalDatabase:
    """An ASMK inverted file over keyframes' local features; ids are insertion counters.

    Upstream: mast3r_slam/retrieval_database.py::RetrievalDatabase (``update``, ``kf_counter``).

    Args:
        codebook: (W, F) visual words (:func:`train_codebook`).
        cfg: :class:`RetrievalConfig`.
    """

    def __init__(
        self,
        codebook: npt.ArrayLike,
        cfg: RetrievalConfig = RetrievalConfig(),  # noqa: B008
    ) -> None:
        cb = as_float_array(codebook, "codebook")
        if cb.ndim != 2 or len(cb) == 0:
            raise ValueError(f"codebook: expected a non-empty (W, F) array, got {cb.shape}")
        self.codebook = cb
        self.cfg = cfg
        self.dim = cb.shape[1]
        self.kf_counter = 0
        self._words: list[IntArray] = []  # per image: word ids (m,)
        self._bits: list[U32Array] = []  # per image: signatures (m, B)
        self._index: tuple[IntArray, IntArray, U32Array, FloatArray] | None = None

    def __len__(self) -> int:
        return self.kf_counter

    def _check(self, features: npt.ArrayLike) -> FloatArray:
        X = as_float_array(features, "features")
        if X.ndim != 2 or X.shape[1] != self.dim or len(X) == 0:
            raise ValueError(f"features: expected a non-empty (n, {self.dim}) array, got {X.shape}")
        return X

    def _inverted_file(self) -> tuple[IntArray, IntArray, U32Array, FloatArray]:
        """All stored (word, image id, bits) sorted by word, and 1/sqrt(n_d) per image."""
        if self._index is None:
            words = np.concatenate(self._words)
            ids = np.repeat(np.arange(len(self._words)), [len(w) for w in self._words])
            bits = np.concatenate(self._bits)
            order = np.argsort(words, kind="stable")
            inv_sqrt_nd = 1.0 / np.sqrt([len(w) for w in self._words])
            self._index = (words[order], ids[order], bits[order], inv_sqrt_nd)
        return self._index

    def _scores_of(self, q_words: IntArray, q_bits: U32Array) -> FloatArray:
        """ASMK scores (n_images,) of a query's aggregated words against every stored image."""
        if self.kf_counter == 0:
            return np.zeros(0)
        words, ids, bits, inv_sqrt_nd = self._inverted_file()
        lo = np.searchsorted(words, q_words, "left")
        cnt = np.searchsorted(words, q_words, "right") - lo
        qi = np.repeat(np.arange(len(q_words)), cnt)
        starts = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt)
        ei = np.arange(len(qi)) + starts
        sim = 1.0 - 2.0 * hamming(q_bits[qi], bits[ei]) / self.dim
        kern = asmk_kernel(sim, self.cfg)
        tot = np.bincount(ids[ei], weights=kern, minlength=self.kf_counter)
        return tot * inv_sqrt_nd / np.sqrt(len(q_words))

    def scores(self, features: npt.ArrayLike) -> FloatArray:
        """ASMK score of ``features`` (query assignment) against every stored image: (n_images,)."""
        X = self._check(features)
        words = quantize(self.codebook, X, self.cfg.query_multiple_assignment)
        return self._scores_of(*aggregate(self.codebook, X, words))

    def _limits(self, k: int | None, min_thresh: float | None) -> tuple[int, float]:
        """``(k, min_thresh)``, each defaulting to the configuration's."""
        return (self.cfg.k if k is None else k), (
            self.cfg.min_thresh if min_thresh is None else min_thresh
        )

    @staticmethod
    def _top(scores: FloatArray, k: int, min_thresh: float) -> list[tuple[int, float]]:
        order = np.argsort(-scores, kind="stable")[: min(k, len(scores))]
        return [(int(i), float(scores[i])) for i in order if scores[i] > min_thresh]

    def query(
        self, features: npt.ArrayLike, k: int | None = None, min_thresh: float | None = None
    ) -> list[tuple[int, float]]:
        """The best ``k`` stored images with ``score > min_thresh``, by descending score.

        Args:
            features: (n, F) local features (``retrieval.select_features``).
            k: number of candidates (default ``cfg.k``).
            min_thresh: score threshold (default ``cfg.min_thresh``).

        Returns:
            [(id, score), ...], best first; empty when the database is empty.
        """
        return self._top(self.scores(features), *self._limits(k, min_thresh))

    def insert(self, features: npt.ArrayLike, words: IntArray | None = None) -> int:
        """Add one image (build assignment) with id ``kf_counter``; returns the id."""
        X = self._check(features)
        if words is None:
            words = quantize(self.codebook, X, self.cfg.build_multiple_assignment)
        w, b = aggregate(self.codebook, X, words)
        self._words.append(w)
        self._bits.append(b)
        self._index = None
        self.kf_counter += 1
        return self.kf_counter - 1

    def update(
        self,
        features: npt.ArrayLike,
        add_after_query: bool = True,
        k: int | None = None,
        min_thresh: float | None = None,
    ) -> list[int]:
        """Query (when the database is non-empty), then optionally insert; upstream ``update``.

        The query's word list (``query_multiple_assignment`` nearest, sorted) is reused for the
        insertion truncated to its first ``build_multiple_assignment`` columns, as upstream does.

        Args:
            features: (n, F) local features of the new keyframe.
            add_after_query: insert the keyframe with id ``kf_counter`` after querying.
            k, min_thresh: see :meth:`query`.

        Returns:
            candidate ids, best first (``score > min_thresh``, at most ``k``).
        """
        X = self._check(features)
        n_assign = max(self.cfg.query_multiple_assignment, self.cfg.build_multiple_assignment)
        words = quantize(self.codebook, X, n_assign)
        found: list[int] = []
        if self.kf_counter > 0:
            q = aggregate(self.codebook, X, words[:, : self.cfg.query_multiple_assignment])
            found = [i for i, _ in self._top(self._scores_of(*q), *self._limits(k, min_thresh))]
        if add_after_query:
            self.insert(X, words[:, : self.cfg.build_multiple_assignment])
        return found
