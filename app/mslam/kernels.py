"""The kernel set — the hot pieces of the SLAM loop and of bundle adjustment, chosen by name.

The SLAM loop (``mslam.system``) and the bundle-adjustment command are written once and call
their hot pieces through a :class:`KernelSet`: the reference modules of ``mslam_ref``
(``"ref"``, NumPy) or their Taichi twins in ``mslam_fast`` (``"fast"``), which have the same
function names and signatures. This is the only place that chooses between them.

A fast module holds only the functions that have a kernel (``mslam_fast.tracking`` has
``linearize`` and ``solve``, not the masks); callers use exactly those through the kernel set
and take everything else (configs, masks, set-up) from ``mslam_ref`` directly.
``mslam_fast`` is imported only when asked for, so a ``ref`` run never imports taichi.

Public names, in reading order:
    KERNEL_SETS, KernelSet, load_kernels
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType, SimpleNamespace

__all__ = ["KERNEL_SETS", "KernelSet", "load_kernels"]

#: Names accepted by :func:`load_kernels` (``mslam run --kernels``, ``mslam ba --kernels``).
KERNEL_SETS = ("ref", "fast")

#: What each piece provides (every name exists in the reference and the fast module).
PIECES = {
    "matching": ("match",),
    "tracking": ("solve",),
    "fusion": ("update_pointmap",),
    "backend": ("solve",),
    "ba.cameras": ("bal_residuals", "bal_linearize", "pinhole_residuals", "pinhole_linearize"),
    "ba.schur": (
        "normal_blocks",
        "jacobi_scale",
        "scaled_normal_blocks",
        "schur_complement",
        "back_substitute",
    ),
    "ba.reduced": ("factor_solve",),
}


@dataclass(frozen=True)
class KernelSet:
    """Module namespaces of the hot pieces.

    Attributes:
        name: ``"ref"`` or ``"fast"``.
        matching: has ``match`` (paper §3.2).
        tracking: has ``solve`` (paper §3.3).
        fusion: has ``update_pointmap`` (paper §3.3, pointmap fusion).
        backend: has ``solve`` (paper §3.5).
        ba: a namespace with ``cameras``, ``schur`` and ``reduced`` modules, the ``kernels``
            argument of ``mslam_ref.ba.lm.optimize``.
        resident: ``mslam_fast.resident`` for ``"fast"`` (matching and fusion with the
            keyframe's arrays kept on the device, docs/matching.md "Device-resident
            arrays"), None for ``"ref"``.
    """

    name: str
    matching: ModuleType
    tracking: ModuleType
    fusion: ModuleType
    backend: ModuleType
    ba: SimpleNamespace
    resident: ModuleType | None = None


def load_kernels(name: str = "fast") -> KernelSet:
    """Import the kernel set ``name`` (``"ref"`` or ``"fast"``).

    Raises:
        ValueError: an unknown name.
    """
    if name not in KERNEL_SETS:
        raise ValueError(
            f"kernels: unknown kernel set {name!r}; choose one of {', '.join(KERNEL_SETS)}"
        )
    package = "mslam_ref" if name == "ref" else "mslam_fast"
    mods = {piece: importlib.import_module(f"{package}.{piece}") for piece in PIECES}
    ba = SimpleNamespace(
        cameras=mods.pop("ba.cameras"), schur=mods.pop("ba.schur"), reduced=mods.pop("ba.reduced")
    )
    resident = importlib.import_module("mslam_fast.resident") if name == "fast" else None
    return KernelSet(name=name, ba=ba, resident=resident, **mods)
