"""The kernel set — the hot pieces of the SLAM loop, chosen by name at run time.

The loop in ``mslam_ref.system`` is written once and calls matching, tracking, fusion and
the backend through a :class:`KernelSet`: the module namespaces of ``mslam_ref`` (``"ref"``,
NumPy) or of ``mslam_fast`` (``"fast"``, Taichi), which have the same function names and
signatures (DEV_NOTES "pairing contract"). ``mslam_fast`` is imported only when asked for, so
a ``ref`` run never imports taichi.

If a fast module is missing (a piece without a fast path yet), the reference module takes its
place and the substitution is recorded in ``KernelSet.fallbacks`` (and in ``summary.json``),
never silently.

Public names, in reading order:
    KERNEL_SETS, KernelSet, load_kernels
"""

from __future__ import annotations

import importlib
import warnings
from dataclasses import dataclass
from types import ModuleType

__all__ = ["KERNEL_SETS", "KernelSet", "load_kernels"]

#: Names accepted by :func:`load_kernels` (and ``mslam run --kernels``).
KERNEL_SETS = ("ref", "fast")

#: The modules a kernel set provides.
_PIECES = ("matching", "tracking", "fusion", "backend")


@dataclass(frozen=True)
class KernelSet:
    """Module namespaces of the hot pieces.

    Attributes:
        name: ``"ref"`` or ``"fast"``.
        matching, tracking, fusion, backend: modules with the reference signatures
            (``match``, ``solve``/``linearize``, ``update_pointmap``, ``solve``/``linearize``).
        fallbacks: pieces that ``"fast"`` could not provide and the reference runs instead.
    """

    name: str
    matching: ModuleType
    tracking: ModuleType
    fusion: ModuleType
    backend: ModuleType
    fallbacks: tuple[str, ...] = ()


def load_kernels(name: str = "fast") -> KernelSet:
    """Import the kernel set ``name`` (``"ref"`` or ``"fast"``).

    Args:
        name: one of :data:`KERNEL_SETS`.

    Returns:
        a :class:`KernelSet`.

    Raises:
        ValueError: unknown name, or a reference module missing.
    """
    if name not in KERNEL_SETS:
        raise ValueError(
            f"kernels: unknown kernel set {name!r}; choose one of {', '.join(KERNEL_SETS)}"
        )
    mods: dict[str, ModuleType] = {}
    fallbacks = []
    for piece in _PIECES:
        if name == "fast":
            try:
                mods[piece] = importlib.import_module(f"mslam_fast.{piece}")
                continue
            except ModuleNotFoundError as exc:
                if exc.name not in (f"mslam_fast.{piece}", "mslam_fast"):
                    raise
                fallbacks.append(piece)
        try:
            mods[piece] = importlib.import_module(f"mslam_ref.{piece}")
        except ModuleNotFoundError as exc:
            if exc.name != f"mslam_ref.{piece}":
                raise
            raise ValueError(f"kernels: module mslam_ref.{piece} is not available") from None
    if fallbacks:
        warnings.warn(
            f"kernel set 'fast': no fast {', '.join(fallbacks)}; using the reference instead",
            RuntimeWarning,
            stacklevel=2,
        )
    return KernelSet(name=name, fallbacks=tuple(fallbacks), **mods)
