"""Find an implementation's function for each kernel: a package or an adapter file.

``--impl`` names either

* a Python package with the reference's module layout and signatures (``mslam_ref``,
  ``mslam_fast``): kernel ``ba.schur.normal_blocks`` is ``PACKAGE.ba.schur.normal_blocks``; a
  module or function the package lacks makes that kernel *absent* (not checked); or
* an adapter file (a path ending in ``.py``) that defines ``KERNELS``, a dict from kernel
  names to callables with the reference's signature; the kernels it leaves out are absent.
  It may define ``NAME`` (a label for the report). An example that wraps a differently named
  API (wxyz quaternions, matrices) is examples/conformance/adapter_example.py.

Public names, in reading order:
    Implementation, load_implementation
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mslam.conformance.kernels import KERNELS

__all__ = ["Implementation", "load_implementation"]


@dataclasses.dataclass(frozen=True)
class Implementation:
    """An implementation under test.

    Attributes:
        name: label shown in the report (package name or the adapter's ``NAME``).
        functions: kernel name -> callable, for the kernels it provides.
    """

    name: str
    functions: dict[str, Callable[..., Any]]


def load_implementation(impl: str) -> Implementation:
    """Resolve ``--impl``: an adapter file (``*.py``) or an importable package name.

    Raises:
        ValueError: a missing or broken adapter file, an unknown kernel name in ``KERNELS``, a
            package that cannot be imported, or an implementation with none of the kernels.
    """
    found = _from_adapter(Path(impl)) if impl.endswith(".py") else _from_package(impl)
    if not found.functions:
        raise ValueError(f"--impl {impl}: provides none of the {len(KERNELS)} kernels")
    return found


def _from_adapter(path: Path) -> Implementation:
    """Execute the adapter file and read its ``KERNELS`` mapping."""
    if not path.is_file():
        raise ValueError(f"--impl {path}: no such adapter file")
    name = f"_mslam_conformance_adapter_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"--impl {path}: not a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # any error inside the user's file is bad input
        raise ValueError(f"--impl {path}: the adapter failed to load: {exc!r}") from exc
    table = getattr(module, "KERNELS", None)
    if not isinstance(table, dict):
        raise ValueError(f"--impl {path}: defines no KERNELS dict (kernel name -> callable)")
    unknown = sorted(set(table) - set(KERNELS))
    if unknown:
        raise ValueError(f"--impl {path}: unknown kernel names in KERNELS: {', '.join(unknown)}")
    bad = sorted(k for k, f in table.items() if not callable(f))
    if bad:
        raise ValueError(f"--impl {path}: KERNELS entries are not callable: {', '.join(bad)}")
    label = str(getattr(module, "NAME", path.name))
    return Implementation(label, {k: table[k] for k in KERNELS if k in table})


def _from_package(package: str) -> Implementation:
    """Look every kernel up as ``package.MODULE.FUNCTION``."""
    try:
        importlib.import_module(package)
    except ImportError as exc:
        raise ValueError(f"--impl {package}: cannot import it ({exc})") from exc
    functions = {}
    for name, kernel in KERNELS.items():
        target = f"{package}.{kernel.module}"
        try:
            module = importlib.import_module(target)
        except ModuleNotFoundError as exc:
            if exc.name is not None and target.startswith(exc.name):
                continue  # the package lacks this module: kernel absent
            raise
        fn = getattr(module, kernel.function, None)
        if callable(fn):
            functions[name] = fn
    return Implementation(package, functions)
