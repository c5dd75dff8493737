"""Upstream's YAML configuration files read, merged and checked (docs/upstream.md §11).

The file-level half of :func:`mslam.config.load_config`: a YAML loader that reads ``1e-8`` as a
float (upstream adds the same resolver), a file read whose errors name the file and line, the
``inherit`` chain resolved recursively (a child overrides its parent key by key, recursively
for sections; a bare ``base`` or ``calib`` names a packaged file in :data:`CONFIG_DIR`), every
key and value type checked against the packaged ``base.yaml`` (an unknown key names the nearest
known one), and integers coerced to floats where ``base.yaml`` has a float.

Public names, in reading order: CONFIG_DIR, YamlLoader, read_yaml, merge, resolve_path,
load_chain, unknown_key, check_against, coerce_numbers
"""

from __future__ import annotations

import copy
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

__all__ = [
    "CONFIG_DIR",
    "YamlLoader",
    "check_against",
    "coerce_numbers",
    "load_chain",
    "merge",
    "read_yaml",
    "resolve_path",
    "unknown_key",
]

#: Folder of the packaged YAML files (``base.yaml``, ``calib.yaml``).
CONFIG_DIR = Path(__file__).with_name("configs")


class YamlLoader(yaml.SafeLoader):
    """SafeLoader that reads ``1e-8`` (no dot) as a float, as upstream's resolver does."""


YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+][0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def read_yaml(path: Path) -> dict[str, Any]:
    """The mapping in YAML file ``path`` (empty for an empty file); a ValueError names the
    file, and the line for invalid YAML."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read config file ({exc.strerror or exc})") from None
    try:
        data = yaml.load(text, Loader=YamlLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = " ".join(str(getattr(exc, "problem", None) or "").split())
        raise ValueError(
            f"{path}:{where} invalid YAML{': ' + problem if problem else ''}"
        ) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(
            f"{path}: a config file must be a mapping of keys, got {type(data).__name__}"
        )
    return data


def merge(parent: dict[str, Any], child: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of ``parent`` with ``child``'s keys laid over it, recursively for sections."""
    out = copy.deepcopy(parent)
    for key, value in child.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def resolve_path(name: str, base_dir: Path) -> Path:
    """The file ``name`` names: an existing absolute path, else the first file found of
    ``base_dir / name``, ``CONFIG_DIR / name`` and ``CONFIG_DIR / name.yaml`` (else the first)."""
    p = Path(name)
    if p.is_absolute() and p.exists():
        return p
    for cand in (base_dir / p, CONFIG_DIR / p, CONFIG_DIR / f"{name}.yaml"):
        if cand.is_file():
            return cand
    return base_dir / p


def load_chain(path: Path, seen: tuple[Path, ...]) -> tuple[dict[str, Any], list[str]]:
    """File ``path`` merged over the files it ``inherit``s, and the files read, parent first;
    ``seen``: the files that include it (a cycle is a ValueError)."""
    path = path.resolve()
    if path in seen:
        raise ValueError(f"{path}: 'inherit' cycle")
    if not path.is_file():
        raise ValueError(f"{path}: config file not found")
    data = read_yaml(path)
    parent_name = data.pop("inherit", None)
    if parent_name is None:
        return data, [str(path)]
    if not isinstance(parent_name, str):
        raise ValueError(f"{path}: 'inherit' must be a file name")
    parent, files = load_chain(resolve_path(parent_name, path.parent), (*seen, path))
    return merge(parent, data), [*files, str(path)]


def _dotted_keys(schema: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Every key of ``schema`` as ``section.key`` (sections included)."""
    out = []
    for key, value in schema.items():
        out.append(f"{prefix}{key}")
        if isinstance(value, dict):
            out += _dotted_keys(value, f"{prefix}{key}.")
    return out


def unknown_key(where: str, dotted: str) -> ValueError:
    """``unknown config key`` with the closest key of base.yaml, if one is close."""
    import difflib

    depth = dotted.count(".")
    keys = [k for k in _dotted_keys(read_yaml(CONFIG_DIR / "base.yaml")) if k.count(".") == depth]
    by_lower = {k.lower(): k for k in keys}
    close = difflib.get_close_matches(dotted.lower(), list(by_lower), n=1, cutoff=0.75)
    hint = f"; did you mean {by_lower[close[0]]}?" if close else ""
    return ValueError(f"{where}: unknown config key {dotted!r}{hint}")


def check_against(
    schema: Mapping[str, Any], data: Mapping[str, Any], where: str, prefix: str = ""
) -> None:
    """Every key of ``data`` exists in ``schema`` with a value of its type (a section, a
    boolean, a number or a string), else a ValueError that names ``where`` and the key."""
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if key not in schema:
            raise unknown_key(where, dotted)
        ref = schema[key]
        if isinstance(ref, dict):
            if not isinstance(value, Mapping):
                raise ValueError(f"{where}: {dotted!r} must be a section (mapping)")
            check_against(ref, value, where, f"{dotted}.")
        elif isinstance(ref, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{where}: {dotted!r} must be true or false, got {value!r}")
        elif isinstance(ref, int | float):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{where}: {dotted!r} must be a number, got {value!r}")
        elif isinstance(ref, str) and not isinstance(value, str):
            raise ValueError(f"{where}: {dotted!r} must be a string, got {value!r}")


def coerce_numbers(schema: Mapping[str, Any], data: dict[str, Any]) -> None:
    """Ints where the schema has floats become floats (``sigma_dist: 10`` → 10.0)."""
    for key, value in data.items():
        ref = schema.get(key)
        if isinstance(ref, dict) and isinstance(value, dict):
            coerce_numbers(ref, value)
        elif isinstance(ref, float) and isinstance(value, int) and not isinstance(value, bool):
            data[key] = float(value)
        elif isinstance(ref, int) and not isinstance(ref, bool) and isinstance(value, float):
            if value.is_integer():
                data[key] = int(value)
