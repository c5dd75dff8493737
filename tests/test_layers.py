"""The three layers and their one-way arrows: application (``mslam``) → ``mslam_fast`` →
``mslam_ref`` (docs/architecture.md).

* ``mslam_ref`` imports with cv2, yaml, tqdm, matplotlib, taichi and torch unimportable, and
  never imports ``mslam_fast`` or ``mslam``;
* ``mslam_fast`` never imports ``mslam`` and uses no ``_private`` name of ``mslam_ref``;
* inside each package the import graph (every import, lazy ones included) has no cycle.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"mslam_ref": ROOT / "reference", "mslam_fast": ROOT / "fast", "mslam": ROOT / "app"}
BLOCKED = ("cv2", "yaml", "tqdm", "matplotlib", "taichi", "torch")


def _modules(package: str) -> dict[str, Path]:
    """Dotted module name -> file, for every module of ``package``."""
    base = PACKAGES[package]
    out = {}
    for path in sorted((base / package).rglob("*.py")):
        parts = list(path.relative_to(base).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(path: Path, modules: dict[str, Path]) -> list[tuple[str, str | None]]:
    """Every import of a file as (module, imported name or None), lazy imports included.

    ``from pkg import sub`` where ``pkg.sub`` is a module gives ``(pkg.sub, None)``."""
    found: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                found.append((sub, None) if sub in modules else (node.module, a.name))
    return found


def _all_modules() -> dict[str, Path]:
    mods: dict[str, Path] = {}
    for package in PACKAGES:
        mods.update(_modules(package))
    return mods


def test_reference_imports_without_the_application_stack() -> None:
    names = sorted(_modules("mslam_ref"))
    script = (
        "import importlib, importlib.abc, sys\n"
        f"BLOCKED = {BLOCKED!r}\n"
        "class Block(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in BLOCKED:\n"
        "            raise ModuleNotFoundError(f'blocked: {name}', name=name)\n"
        "sys.meta_path.insert(0, Block())\n"
        f"for m in {names!r}:\n"
        "    importlib.import_module(m)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('mslam', 'mslam_fast', *BLOCKED))\n"
        "assert not bad, bad\n"
        "print('ok', len(sys.modules))\n"
    )
    env_path = str(PACKAGES["mslam_ref"])
    res = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"},
        check=False,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.startswith("ok")


@pytest.mark.parametrize(
    "package,forbidden",
    [("mslam_ref", ("mslam_fast", "mslam", *BLOCKED)), ("mslam_fast", ("mslam",))],
)
def test_no_import_against_the_arrows(package: str, forbidden: tuple[str, ...]) -> None:
    mods = _all_modules()
    bad = [
        f"{name}: {imp}"
        for name, path in _modules(package).items()
        for imp, _ in _imports(path, mods)
        if imp.split(".")[0] in forbidden
    ]
    assert not bad, bad


def test_fast_uses_only_public_reference_names() -> None:
    mods = _all_modules()
    bad = []
    for name, path in _modules("mslam_fast").items():
        tree = ast.parse(path.read_text(), str(path))
        ref_aliases = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mslam_ref"):
                for a in node.names:
                    if a.name.startswith("_") or any(
                        p.startswith("_") for p in node.module.split(".")
                    ):
                        bad.append(f"{name}: from {node.module} import {a.name}")
                    if f"{node.module}.{a.name}" in mods:
                        ref_aliases.add(a.asname or a.name)
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("mslam_ref"):
                        ref_aliases.add(a.asname or a.name.split(".")[0])
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in ref_aliases
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                bad.append(f"{name}: {node.value.id}.{node.attr}")
    assert not bad, bad


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph as a list of nodes, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return [*stack[stack.index(m) :], m]
            if m not in state and (found := visit(m)):
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n)):
            return found
    return None


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_import_graph_has_no_cycle(package: str) -> None:
    mods = _modules(package)
    graph = {
        name: {imp for imp, _ in _imports(path, mods) if imp in mods and imp != name}
        for name, path in mods.items()
    }
    assert _cycle(graph) is None, f"import cycle: {' -> '.join(_cycle(graph) or [])}"


def test_cycle_finder_finds_a_cycle() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


#: The application's own layers, bottom to top (docs/architecture.md): a module imports only
#: from its own layer or below. The package ``mslam`` itself (its lazy public names) is the API.
APP_LAYERS: tuple[tuple[str, ...], ...] = (
    ("mslam.atomic", "mslam.errors", "mslam.outdir"),
    (
        "mslam.ply",
        "mslam.formats",
        "mslam.bal",
        "mslam.g2o_ba",
        "mslam.kernels",
        "mslam.evaluate",
        "mslam.rotation_metrics",
        "mslam.baselines",
        "mslam.device",
    ),
    ("mslam.conformance",),
    ("mslam.datasets", "mslam.priors", "mslam.map_metrics"),
    ("mslam.config", "mslam.config_ranges", "mslam.config_yaml"),
    ("mslam.system",),
    ("mslam.export",),
    ("mslam.api",),
    ("mslam.commands", "mslam.cli"),
)


def _app_layer(module: str) -> int | None:
    """The layer index of an ``mslam`` module, None for the package itself."""
    for rank, prefixes in enumerate(APP_LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return rank
    return None


def test_every_app_module_has_a_layer() -> None:
    missing = [m for m in _modules("mslam") if m != "mslam" and _app_layer(m) is None]
    assert not missing, f"add these modules to APP_LAYERS: {missing}"


def test_no_back_arrow_inside_the_application() -> None:
    """Nothing imports from a layer above its own: the commands and the CLI sit on top, and
    no module below them imports them (writers use ``mslam.atomic``)."""
    mods = _modules("mslam")
    bad = []
    for name, path in mods.items():
        rank = _app_layer(name)
        if rank is None:
            continue
        for imp, _ in _imports(path, mods):
            target = _app_layer(imp) if imp.split(".")[0] == "mslam" else None
            if target is not None and target > rank:
                bad.append(f"{name} -> {imp}")
    assert not bad, bad


def test_back_arrow_finder_sees_a_planted_import(tmp_path: Path) -> None:
    path = tmp_path / "m.py"
    path.write_text("from mslam.commands import UserError\n")
    imports = _imports(path, _modules("mslam"))
    assert any(_app_layer(imp) == len(APP_LAYERS) - 1 for imp, _ in imports)
