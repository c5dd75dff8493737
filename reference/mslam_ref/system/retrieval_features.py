"""docs/upstream.md §7.1–7.2 — the system's retrieval index: keyframe features and the codebook.

Upstream's retrieval database scores keyframes by ASMK over encoder tokens with a codebook
trained offline (64k words, shipped with the checkpoint). We have neither, so the system
keeps a :class:`mslam_ref.retrieval.RetrievalDatabase` whose codebook is trained, at the
first keyframe, by k-means on that keyframe's dense descriptors (a sample of at most
``train_samples`` pixels, seeded, so runs stay deterministic). A keyframe's features are its
top-``nfeat`` descriptors by descriptor confidence Q (``retrieval.select_features``).

Database ids equal keyframe indices: every keyframe is inserted exactly once, in order, and a
failed relocalisation inserts nothing (docs/upstream.md §7.2).

Public names, in reading order:
    RetrievalIndex
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_ref.config import RetrievalSettings

__all__ = ["RetrievalIndex"]


class RetrievalIndex:
    """Retrieval database with a lazily trained codebook (see the module docstring).

    Args:
        settings: ``retrieval.k`` and ``retrieval.min_thresh``.
        nfeat: features kept per keyframe (None: the retrieval module's default).
        n_clusters: codebook size.
        train_samples: descriptors sampled from the first keyframe to train the codebook.
        seed: k-means seed.
    """

    def __init__(
        self,
        settings: RetrievalSettings,
        nfeat: int | None = None,
        n_clusters: int = 64,
        train_samples: int = 4096,
        seed: int = 0,
    ) -> None:
        self.settings = settings
        self.n_clusters, self.train_samples, self.seed = n_clusters, train_samples, seed
        self._nfeat = nfeat
        self.db: Any = None
        self._train: np.ndarray | None = None

    @property
    def nfeat(self) -> int:
        """Features per keyframe."""
        if self._nfeat is None:
            from mslam_ref import retrieval

            self._nfeat = int(getattr(retrieval.RetrievalConfig(), "nfeat", 300))
        return self._nfeat

    def __len__(self) -> int:
        return 0 if self.db is None else int(getattr(self.db, "kf_counter", len(self.db)))

    def features(self, D: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Top-``nfeat`` descriptors of one image by descriptor confidence: (nfeat, F)."""
        from mslam_ref import retrieval

        if self._train is None and self.db is None:
            flat = D.reshape(-1, D.shape[-1])
            rng = np.random.default_rng(self.seed)
            take = rng.choice(len(flat), size=min(self.train_samples, len(flat)), replace=False)
            self._train = flat[np.sort(take)]
        return np.asarray(retrieval.select_features(D, Q, self.nfeat))

    def _ensure_db(self) -> Any:
        if self.db is None:
            from mslam_ref import retrieval

            if self._train is None:
                raise RuntimeError("retrieval: features() must be called before the first insert")
            n_clusters = min(self.n_clusters, len(self._train))
            codebook = retrieval.train_codebook(self._train, n_clusters, self.seed)
            self.db = retrieval.RetrievalDatabase(codebook)
        return self.db

    def insert(self, features: np.ndarray) -> list[int]:
        """Query then insert (upstream ``update(add_after_query=True)``); returns the candidates."""
        return self.update(features)

    def update(self, features: np.ndarray) -> list[int]:
        """Candidate keyframe ids for ``features`` (query first), then insert them."""
        db = self._ensure_db()
        out = db.update(features, True, self.settings.k, self.settings.min_thresh)
        return [int(i) for i in out]

    def query(self, features: np.ndarray) -> list[int]:
        """Candidate ids (best first) without inserting (relocalisation)."""
        if self.db is None:
            return []
        res = self.db.query(features, self.settings.k, self.settings.min_thresh)
        return [int(r[0]) if isinstance(r, tuple | list) else int(r) for r in res]
