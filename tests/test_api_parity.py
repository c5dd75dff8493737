"""Every public name of ``mslam_fast.<module>`` exists in ``mslam_ref.<module>`` with the same
parameters (names, kinds and defaults; annotations are not compared)."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import mslam_fast

FAST_MODULES = sorted(
    m.name
    for m in pkgutil.walk_packages(mslam_fast.__path__, "mslam_fast.")
    if not any(part.startswith("_") for part in m.name.split("."))
)


def _params(fn: object) -> list[tuple[str, object, object]]:
    sig = inspect.signature(fn)  # type: ignore[arg-type]
    return [(p.name, p.kind, p.default) for p in sig.parameters.values()]


def test_fast_has_modules() -> None:
    assert "mslam_fast.sim3" in FAST_MODULES


@pytest.mark.parametrize("fast_name", FAST_MODULES)
def test_public_names_match_reference(fast_name: str) -> None:
    fast_mod = importlib.import_module(fast_name)
    ref_mod = importlib.import_module(fast_name.replace("mslam_fast", "mslam_ref", 1))
    public = getattr(fast_mod, "__all__", None)
    assert public, f"{fast_name} must declare __all__"
    for name in public:
        assert hasattr(ref_mod, name), f"{fast_name}.{name} has no reference twin"
        f, r = getattr(fast_mod, name), getattr(ref_mod, name)
        if inspect.isclass(r) and f is r:
            continue  # shared dataclass re-exported from the reference
        if callable(f) and callable(r):
            assert _params(f) == _params(r), f"signature of {fast_name}.{name} differs"
