"""docs/upstream.md §11 — configuration: upstream's YAML files, ``inherit``, command-line overrides.

Upstream keeps every setting in ``config/*.yaml`` (``base.yaml`` and files that ``inherit`` it,
e.g. ``calib.yaml``) and reads them into one global dictionary. Here the same files are read
into a frozen :class:`SlamConfig` that is passed explicitly; the typed per-module configs
(``MatchingConfig``, ``TrackingConfig``, ``FusionConfig``, ``BackendConfig``) are built from
their YAML sections on demand, with upstream's key names.

Rules:

* ``inherit: FILE`` is resolved recursively (relative to the including file; a bare ``base`` or
  ``calib`` names the packaged files in ``mslam/configs``); the child overrides the parent
  key by key, recursively for sections.
* Floats such as ``1e-8`` parse as floats (upstream adds a YAML float resolver for this).
* Every key must exist in the packaged ``base.yaml``: an unknown key (a typo) is a
  ``ValueError`` naming the file, the key and the nearest known key, as is a wrong type.
* Overrides ``SECTION.KEY=VALUE`` (``--set tracking.Q_conf=2.0``) are parsed as YAML scalars and
  applied last.
* Every numeric value is then checked against its stated range (finite, integral where the key
  counts something, positive where it divides or scales) in ``mslam.config_ranges``; the
  error names the key and the ``--set`` or file it came from.

Reading, merging and checking the files is :mod:`mslam.config_yaml`'s part.

Public names, in reading order: SlamConfig, DatasetConfig, RelocConfig, load_config,
parse_override, config_to_dict, CONFIG_DIR
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mslam.config_yaml import (
    CONFIG_DIR,
    YamlLoader,
    check_against,
    coerce_numbers,
    load_chain,
    merge,
    read_yaml,
    resolve_path,
    unknown_key,
)

__all__ = [
    "CONFIG_DIR",
    "DatasetConfig",
    "RelocConfig",
    "SlamConfig",
    "config_to_dict",
    "load_config",
    "parse_override",
]


@dataclass(frozen=True)
class DatasetConfig:
    """``dataset.*`` keys (docs/upstream.md §10.3, §11).

    Attributes:
        subsample: keep every n-th frame (>= 1).
        img_downsample: upstream's output stride; unsupported upstream, must be 1.
        center_principle_point: re-centre the principal point when undistorting (upstream key,
            spelling kept).
        long_side: mslam only — resize frames so that the long side has this many pixels
            (0 keeps the source resolution). Upstream always resizes to 512 for the network;
            on a CPU a smaller size keeps runs short.
    """

    subsample: int = 1
    img_downsample: int = 1
    center_principle_point: bool = True
    long_side: int = 0


@dataclass(frozen=True)
class RelocConfig:
    """``reloc.*`` keys (docs/upstream.md §9, ``mslam.system.reloc``): the stricter match
    fraction, and ``strict``: whether the best-ranked candidate must pass (False: any verified
    candidate relocalises the frame; docs/system.md, "Relocalisation")."""

    min_match_frac: float = 0.3
    strict: bool = False


@dataclass(frozen=True)
class SlamConfig:
    """The whole resolved configuration of a run (upstream's global ``config`` dict, typed).

    Attributes:
        use_calib: calibrated mode (pixel + log-depth residuals, points on known rays).
        single_thread: upstream's sequential evaluation mode (the default here): the
            backend runs after each new keyframe before the next frame. False runs it in a
            background thread (``mslam.system.worker``; upstream: a separate process).
        dataset, reloc: typed sections of the application.
        sections: the resolved YAML as nested plain dicts (``matching``, ``tracking``,
            ``local_opt``, ...), the source of :meth:`matching`, :meth:`tracking`, ...
        sources: the files read, parent first.
    """

    use_calib: bool = False
    single_thread: bool = True
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    reloc: RelocConfig = field(default_factory=RelocConfig)
    sections: Mapping[str, Any] = field(default_factory=dict)
    sources: tuple[str, ...] = ()

    def _typed(self, module: str, cls_name: str, section: str) -> Any:
        cls = getattr(importlib.import_module(f"mslam_ref.{module}"), cls_name)
        return self._section_as(cls, section)

    def _section_as(self, cls: type, section: str) -> Any:
        """``cls`` (a dataclass) from the section's keys it has; the rest keep its defaults."""
        keys = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in dict(self.sections.get(section, {})).items() if k in keys}
        return cls(**values)

    def matching(self) -> Any:
        """``mslam_ref.matching.MatchingConfig`` from ``matching.*``."""
        return self._typed("matching", "MatchingConfig", "matching")

    def tracking(self) -> Any:
        """``mslam_ref.tracking.TrackingConfig`` from ``tracking.*``."""
        return self._typed("tracking", "TrackingConfig", "tracking")

    def fusion(self) -> Any:
        """``mslam_ref.fusion.FusionConfig`` from ``tracking.filtering_mode/filtering_score``."""
        return self._typed("fusion", "FusionConfig", "tracking")

    def backend(self) -> Any:
        """``mslam_ref.backend.BackendConfig`` from ``local_opt.*``."""
        return self._typed("backend", "BackendConfig", "local_opt")

    def _grid_stride(self, section: str, key: str, shape: tuple[int, int]) -> int:
        budget = int(dict(self.sections.get(section, {})).get(key, 0))
        if budget <= 0:
            return 1
        # The nearest stride: the grid holds half to twice the budget once the stride exceeds 1.
        return max(1, round((shape[0] * shape[1] / budget) ** 0.5))

    def backend_pixel_stride(self, shape: tuple[int, int]) -> int:
        """Stride of the pixel grid that keeps about ``local_opt.pixels_per_edge`` residuals
        per directed block of an (H, W) pointmap (1 = every pixel, also when the key is 0).
        The graph step matches only these pixels of each edge."""
        return self._grid_stride("local_opt", "pixels_per_edge", shape)

    def tracking_pixel_stride(self, shape: tuple[int, int]) -> int:
        """Stride of the keyframe-pixel grid that tracking matches and solves on: about
        ``tracking.pixels_per_frame`` pixels of an (H, W) keyframe (1 = every pixel, also
        when the key is 0, upstream's choice)."""
        return self._grid_stride("tracking", "pixels_per_frame", shape)

    def keyframe_cell_stride(self, shape: tuple[int, int]) -> int:
        """Side of the cells in which the new-keyframe test counts distinct frame pixels: about
        ``tracking.keyframe_cells`` cells over an (H, W) frame, never finer than the tracking
        grid (its stride when the key is 0)."""
        return max(self._grid_stride("tracking", "keyframe_cells", shape),
                   self.tracking_pixel_stride(shape))  # fmt: skip

    def keyframe_first_ratio(self) -> float:
        """``tracking.keyframe_first_ratio`` (0 when absent: upstream's fixed threshold)."""
        return float(dict(self.sections.get("tracking", {})).get("keyframe_first_ratio", 0.0))

    def retrieval(self) -> Any:
        """``mslam_ref.retrieval.RetrievalConfig`` from ``retrieval.*`` (the one place the
        retrieval settings live; keys not in the YAML keep the dataclass defaults)."""
        return self._typed("retrieval", "RetrievalConfig", "retrieval")

    def rgbd_prior(self) -> Any:
        """``mslam.priors.rgbd.RGBDPriorConfig`` from ``rgbd_prior.*`` (keys not in the YAML
        keep the dataclass defaults); ``rgbd_prior.descriptors`` is its ``desc.kind``."""
        from mslam.priors.rgbd import RGBDPriorConfig

        cfg = self._section_as(RGBDPriorConfig, "rgbd_prior")
        kind = dict(self.sections.get("rgbd_prior", {})).get("descriptors")
        if kind is None:
            return cfg
        if kind not in ("dense", "separable"):
            raise ValueError(f"descriptors: expected 'dense' or 'separable', got {kind!r}")
        return dataclasses.replace(cfg, desc=dataclasses.replace(cfg.desc, kind=kind))

    def twoview_prior(self) -> Any:
        """``mslam.priors.twoview.TwoViewPriorConfig`` from ``twoview_prior.*``."""
        from mslam.priors.twoview import TwoViewPriorConfig

        return self._section_as(TwoViewPriorConfig, "twoview_prior")

    def mast3r_prior(self) -> Any:
        """``mslam.priors.mast3r.Mast3rConfig`` from ``mast3r_prior.*`` (checkpoint, input
        size, device, cache bound; keys not in the YAML keep the dataclass defaults)."""
        from mslam.priors.mast3r import Mast3rConfig

        return self._section_as(Mast3rConfig, "mast3r_prior")


def parse_override(text: str) -> tuple[list[str], Any]:
    """Parse ``SECTION.KEY=VALUE`` into the key path and a YAML-typed value.

    Example: ``"tracking.Q_conf=2.0"`` → ``(["tracking", "Q_conf"], 2.0)``.
    """
    if "=" not in text:
        raise ValueError(f"--set {text!r}: expected KEY=VALUE, e.g. tracking.Q_conf=2.0")
    key, raw = text.split("=", 1)
    path = [p for p in key.strip().split(".") if p]
    if not path:
        raise ValueError(f"--set {text!r}: empty key")
    try:
        value = yaml.load(raw.strip(), Loader=YamlLoader) if raw.strip() else None
    except yaml.YAMLError:
        raise ValueError(f"--set {text!r}: value is not a YAML scalar") from None
    return path, value


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> SlamConfig:
    """Read a config file (default: the packaged ``base.yaml``) and apply overrides.

    Upstream: mast3r_slam/config.py::load_config (``inherit`` resolution, float resolver).

    Args:
        path: a YAML file, or the name of a packaged file (``base``, ``calib``, ``rgbd``,
            ``rgbd_256``, ``rgbd_512``, ...), or None for base.
        overrides: ``SECTION.KEY=VALUE`` strings applied after the files.

    Returns:
        the resolved :class:`SlamConfig`.

    Raises:
        ValueError: unreadable or invalid file, unknown key, wrong value type, naming the file.
    """
    overrides = list(overrides)
    base_path = CONFIG_DIR / "base.yaml"
    schema = read_yaml(base_path)
    if path is None:
        data, files = copy.deepcopy(schema), [str(base_path)]
    else:
        p = resolve_path(str(path), Path.cwd())
        data, files = load_chain(p, ())
        check_against(schema, data, str(p))
        data = merge(schema, data)
    set_by: dict[str, str] = {}
    for text in overrides:
        keys, value = parse_override(text)
        set_by[".".join(keys)] = f"--set {text}"
        node = data
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                raise unknown_key(f"--set {text!r}", ".".join(keys))
            node = node[k]
        if keys[-1] not in node or isinstance(node[keys[-1]], dict):
            raise unknown_key(f"--set {text!r}", ".".join(keys))
        node[keys[-1]] = value
    check_against(schema, data, "config overrides" if overrides else files[-1])
    coerce_numbers(schema, data)
    from mslam.config_ranges import check_ranges

    check_ranges(data, set_by, files[-1])  # every value against its stated range, one place
    ds = DatasetConfig(**data["dataset"])
    cfg = SlamConfig(
        use_calib=bool(data["use_calib"]),
        single_thread=bool(data["single_thread"]),
        dataset=ds,
        reloc=RelocConfig(**data["reloc"]),
        sections={k: v for k, v in data.items() if isinstance(v, dict)},
        sources=tuple(files),
    )
    try:  # the prior's words (sift/orb, dense/separable) now, whichever prior the run uses
        cfg.rgbd_prior()
    except ValueError as exc:
        raise ValueError(f"rgbd_prior.{exc}") from None
    try:  # the network input size is 224 or 512 (the range check admits [224, 512])
        cfg.mast3r_prior()
    except ValueError as exc:
        where = set_by.get("mast3r_prior.size", files[-1])
        raise ValueError(f"{where}: mast3r_prior.{exc}") from None
    return cfg


def config_to_dict(cfg: SlamConfig) -> dict[str, Any]:
    """The resolved configuration as nested plain dicts (what ``summary.json`` records)."""
    out: dict[str, Any] = {"use_calib": cfg.use_calib, "single_thread": cfg.single_thread}
    out.update(copy.deepcopy(dict(cfg.sections)))
    return out
