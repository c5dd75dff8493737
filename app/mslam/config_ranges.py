"""The stated range of every numeric configuration key, checked in one place (docs/upstream.md).

``load_config`` calls :func:`check_ranges` on the merged configuration (files, then ``--set``
overrides). Every number must be finite; keys marked ``int`` must be integral (``1.0`` is
accepted as 1, ``1.5`` is not); each value must lie in its range. The error names the key, the
value, the range, and where the value came from (``--set KEY=VALUE`` or the config file).

Public names, in reading order: RANGES, describe, check_ranges.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

__all__ = ["RANGES", "check_ranges", "describe"]

_INF = math.inf

#: dotted key -> (integral, low, high, low_open); ``low_open``: the low bound is excluded.
#: ``dataset.long_side`` is special: 0 (keep the source size) or in [16, 8192];
#: ``mast3r_prior.size`` must also be 224 or 512 (``Mast3rConfig``, checked by ``load_config``).
RANGES: dict[str, tuple[bool, float, float, bool]] = {
    "dataset.subsample": (True, 1, 10_000, False),
    "dataset.img_downsample": (True, 1, 1, False),
    "dataset.long_side": (True, 16, 8192, False),
    "matching.max_iter": (True, 1, 1000, False),
    "matching.lambda_init": (False, 0, _INF, True),
    "matching.convergence_thresh": (False, 0, _INF, True),
    "matching.dist_thresh": (False, 0, _INF, True),
    "matching.radius": (True, 0, 64, False),
    "matching.dilation_max": (True, 1, 64, False),
    "tracking.min_match_frac": (False, 0, 1, False),
    "tracking.max_iters": (True, 1, 10_000, False),
    "tracking.C_conf": (False, 0, _INF, False),
    "tracking.Q_conf": (False, 0, _INF, False),
    "tracking.rel_error": (False, 0, _INF, True),
    "tracking.delta_norm": (False, 0, _INF, True),
    "tracking.huber": (False, 0, _INF, True),
    "tracking.match_frac_thresh": (False, 0, 1, False),
    "tracking.sigma_ray": (False, 0, _INF, True),
    "tracking.sigma_dist": (False, 0, _INF, True),
    "tracking.sigma_pixel": (False, 0, _INF, True),
    "tracking.sigma_depth": (False, 0, _INF, True),
    "tracking.sigma_point": (False, 0, _INF, True),
    "tracking.pixel_border": (True, -10_000, 10_000, False),
    "tracking.depth_eps": (False, 0, _INF, True),
    "tracking.pixels_per_frame": (True, 0, 1_000_000_000, False),
    "tracking.keyframe_cells": (True, 0, 1_000_000_000, False),
    "tracking.keyframe_first_ratio": (False, 0, 1, False),
    "tracking.min_pair_parallax_px": (False, 0, _INF, False),
    "local_opt.pin": (True, 1, 1000, False),
    "local_opt.window_size": (False, 0, _INF, True),
    "local_opt.C_conf": (False, 0, _INF, False),
    "local_opt.Q_conf": (False, 0, _INF, False),
    "local_opt.min_match_frac": (False, 0, 1, False),
    "local_opt.pixel_border": (True, -10_000, 10_000, False),
    "local_opt.depth_eps": (False, 0, _INF, True),
    "local_opt.max_iters": (True, 1, 10_000, False),
    "local_opt.sigma_ray": (False, 0, _INF, True),
    "local_opt.sigma_dist": (False, 0, _INF, True),
    "local_opt.sigma_pixel": (False, 0, _INF, True),
    "local_opt.sigma_depth": (False, 0, _INF, True),
    "local_opt.sigma_point": (False, 0, _INF, True),
    "local_opt.delta_norm": (False, 0, _INF, True),
    "local_opt.pixels_per_edge": (True, 0, 1_000_000_000, False),
    "retrieval.k": (True, 1, 100, False),
    "retrieval.min_thresh": (False, 0, _INF, False),
    "reloc.min_match_frac": (False, 0, 1, False),
    "recovery.max_lost_frames": (True, 0, 1_000_000, False),
    "recovery.max_refusals": (True, 0, 1_000_000, False),
    "recovery.refusal_window": (True, 1, 1_000_000, False),
    "recovery.merge_maps": (True, 0, 1, False),
    "rgbd_prior.n_features": (True, 10, 100_000, False),
    "rgbd_prior.detect_min_width": (True, 0, 8192, False),
    "rgbd_prior.detect_max_width": (True, 0, 8192, False),
    "rgbd_prior.icp_iters": (True, 0, 1000, False),
    "rgbd_prior.icp_points": (True, 100, 10_000_000, False),
    "mast3r_prior.size": (True, 224, 512, False),
    "mast3r_prior.cache_bytes": (True, 0, 1_000_000_000_000, False),
    "output.C_conf_threshold": (False, 0, _INF, False),
    "output.scale_tolerance": (False, 0, _INF, False),
}


def describe(key: str) -> str:
    """The stated range of ``key`` in words, e.g. ``"an integer in [1, 1000]"``."""
    integral, lo, hi, lo_open = RANGES[key]
    kind = "an integer" if integral else "a finite number"
    left = "(" if lo_open else "["
    right = ")" if hi == _INF else "]"
    text = f"{kind} in {left}{lo:g}, {'inf' if hi == _INF else f'{hi:g}'}{right}"
    return "0 or " + text if key == "dataset.long_side" else text


def _ok(key: str, value: Any) -> bool:
    integral, lo, hi, lo_open = RANGES[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    if not math.isfinite(value) or (integral and value != int(value)):
        return False
    if key == "dataset.long_side" and value == 0:
        return True
    return (lo < value if lo_open else lo <= value) and value <= hi


def check_ranges(data: Mapping[str, Any], where: Mapping[str, str], default_where: str) -> None:
    """Raise ``ValueError`` for the first value outside its stated range.

    Args:
        data: the merged configuration (nested dicts).
        where: dotted key -> where it was set (``--set tracking.huber=0``), for overrides.
        default_where: the config file named for every other key.
    """
    for key in RANGES:
        section, name = key.split(".")
        node = data.get(section)
        if not isinstance(node, Mapping) or name not in node:
            continue
        value = node[name]
        if not _ok(key, value):
            src = where.get(key, default_where)
            raise ValueError(f"{src}: {key} must be {describe(key)}, got {value!r}")
