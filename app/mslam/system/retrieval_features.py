"""Paper §3.4 — the system's retrieval index: keyframe features and the codebook.

Upstream's retrieval database scores keyframes by ASMK over encoder tokens with a codebook
trained offline (64k words, shipped with the checkpoint). We have neither, so the system
keeps a :class:`mslam_ref.retrieval_database.RetrievalDatabase` whose codebook is trained, at
the first keyframe, by k-means on that keyframe's dense descriptors (a sample of at most
``RetrievalConfig.codebook_samples`` pixels, seeded, so runs stay deterministic). A keyframe's features are its
top-``nfeat`` descriptors by descriptor confidence Q (``retrieval.select_features``).

Database ids equal keyframe indices: every keyframe is inserted exactly once, in order, and a
failed relocalisation inserts nothing.

Public names, in reading order:
    RetrievalIndex
"""

from __future__ import annotations

import numpy as np

from mslam_ref import retrieval
from mslam_ref.retrieval_database import RetrievalDatabase

__all__ = ["RetrievalIndex"]


class RetrievalIndex:
    """Retrieval database with a lazily trained codebook (see the module docstring).

    Args:
        cfg: the retrieval configuration (``retrieval.*``: ``k``, ``min_thresh``, ``nfeat``,
            the codebook's size, sample and seed).
    """

    def __init__(self, cfg: retrieval.RetrievalConfig) -> None:
        self.cfg = cfg
        self.db: RetrievalDatabase | None = None
        self._train: np.ndarray | None = None

    def __len__(self) -> int:
        return 0 if self.db is None else len(self.db)

    def features(self, D: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Top-``nfeat`` descriptors of one image by descriptor confidence: (nfeat, F)."""
        if self._train is None and self.db is None:
            flat = D.reshape(-1, D.shape[-1])
            rng = np.random.default_rng(self.cfg.seed)
            n = min(self.cfg.codebook_samples, len(flat))
            self._train = flat[np.sort(rng.choice(len(flat), size=n, replace=False))]
        return np.asarray(retrieval.select_features(D, Q, self.cfg.nfeat))

    def _ensure_db(self) -> RetrievalDatabase:
        if self.db is None:
            if self._train is None:
                raise RuntimeError("retrieval: features() must be called before the first insert")
            n_clusters = min(self.cfg.codebook_size, len(self._train))
            codebook = retrieval.train_codebook(self._train, n_clusters, self.cfg.seed)
            self.db = RetrievalDatabase(codebook, self.cfg)
        return self.db

    def update(self, features: np.ndarray) -> list[int]:
        """Candidate keyframe ids for ``features`` (query first), then insert them
        (upstream ``update(add_after_query=True)``)."""
        return [int(i) for i in self._ensure_db().update(features, True)]

    def query(self, features: np.ndarray) -> list[int]:
        """Candidate ids (best first) without inserting (relocalisation)."""
        if self.db is None:
            return []
        return [int(i) for i, _ in self.db.query(features)]
