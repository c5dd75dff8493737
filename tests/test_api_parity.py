"""Every public name of ``mslam_fast.<module>`` is a Taichi twin of ``mslam_ref.<module>``:
the reference has it, with the same parameters (names, kinds and defaults; annotations are
not compared), and the fast name is its own function, never the reference object forwarded.
The kernel set's pieces exist on both sides. ``mslam_fast.resident`` is the one module
without a twin: its entries keep arrays on the device between calls, and each has the
parameters of the reference function it stands for."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import mslam_fast
from mslam.kernels import PIECES

#: Public modules of ``mslam_fast`` that are not twins: the device-resident entries.
DEVICE_ENTRIES = {"mslam_fast.resident"}

FAST_MODULES = sorted(
    m.name
    for m in pkgutil.walk_packages(mslam_fast.__path__, "mslam_fast.")
    if not any(part.startswith("_") for part in m.name.split(".")) and m.name not in DEVICE_ENTRIES
)


def _params(fn: object) -> list[tuple[str, object, object]]:
    sig = inspect.signature(fn)  # type: ignore[arg-type]
    return [(p.name, p.kind, p.default) for p in sig.parameters.values()]


def test_fast_has_modules() -> None:
    assert "mslam_fast.sim3" in FAST_MODULES


@pytest.mark.parametrize("fast_name", FAST_MODULES)
def test_public_names_are_twins(fast_name: str) -> None:
    fast_mod = importlib.import_module(fast_name)
    ref_mod = importlib.import_module(fast_name.replace("mslam_fast", "mslam_ref", 1))
    public = getattr(fast_mod, "__all__", None)
    assert public, f"{fast_name} must declare __all__"
    for name in public:
        assert hasattr(ref_mod, name), f"{fast_name}.{name} has no reference twin"
        f, r = getattr(fast_mod, name), getattr(ref_mod, name)
        if inspect.ismodule(f):
            assert inspect.ismodule(r), f"{fast_name}.{name}: module vs {type(r)}"
            continue
        assert f is not r, f"{fast_name}.{name} forwards the reference object"
        assert callable(f) and callable(r), f"{fast_name}.{name}: not a function"
        assert _params(f) == _params(r), f"signature of {fast_name}.{name} differs"


@pytest.mark.parametrize("piece", sorted(PIECES))
def test_kernel_set_pieces_exist_in_both(piece: str) -> None:
    for package in ("mslam_ref", "mslam_fast"):
        module = importlib.import_module(f"{package}.{piece}")
        for name in PIECES[piece]:
            assert name in module.__all__, f"{package}.{piece}.{name} missing"


def test_resident_entries_have_the_reference_parameters() -> None:
    from mslam_fast import resident
    from mslam_ref import fusion, matching

    pairs = [
        (resident.ResidentMatcher.match, matching.match),
        (resident.ResidentFusion.update_pointmap, fusion.update_pointmap),
    ]
    for method, ref in pairs:
        assert _params(method)[1:] == _params(ref), method.__qualname__  # [0] is self
