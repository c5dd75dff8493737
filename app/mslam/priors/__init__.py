"""Paper §3 / docs/upstream.md §2 — where pointmaps come from: the prior protocol and its implementations.

* :mod:`mslam.priors.base` — ``PairPrediction``, the ``Prior`` protocol, ``check_prediction``;
* :mod:`mslam.priors.synthetic` — ground truth plus a documented noise model;
* :mod:`mslam.priors.rgbd` — real RGB-D frames, relative pose from features + depth + PnP;
* :mod:`mslam.priors.twoview` — RGB only: two-view geometry from dense flow;
* :mod:`mslam.priors.mast3r` — adapter to a user's MASt3R install and checkpoint (torch),
  loaded by :mod:`mslam.priors.mast3r_load`;
* :mod:`mslam.priors.descriptors` — the patch descriptors and their confidence Q
  (``descriptor_Q``) of the synthetic, RGB-D and two-view priors;
* :mod:`mslam.priors.cache` — ``ByteLRU``, the byte-bounded per-frame cache of every prior.

Submodules are imported on demand (``from mslam.priors.synthetic import SyntheticPrior``).
"""

from mslam.priors.base import DESC_DIM, PairPrediction, Prior, check_prediction

__all__ = ["DESC_DIM", "PairPrediction", "Prior", "check_prediction"]
