"""MkDocs hooks: the tutorials as executed notebooks on the documentation site.

``tutorials/NN_*.py`` (jupytext percent format) are executed once with nbclient into
``build/notebooks/tutorials/NN_*.ipynb`` and handed to mkdocs-jupyter, which renders them with
their outputs (figures inline). An executed notebook is reused while its key — a hash of the
tutorial and of every Python source of the packages — is unchanged, so ``pytest``'s notebook
test (tests/test_notebooks.py, which writes the same cache) and a later site build in the same
checkout execute each tutorial only once. A failing cell fails the build.

The site loads nothing from the network: MathJax 3 comes from the ``django-static-mathjax``
package (the ``docs`` extra: MathJax's own files, no Django) and is copied into
``javascripts/mathjax/`` of the site; ``docs/javascripts/mathjax.js`` configures it. The
notebook template's dead MathJax 2 block (an empty ``<script src="">`` and a v2 config) is
removed from the tutorial pages.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import tempfile
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "build" / "notebooks"
TUTORIALS = ROOT / "tutorials"
SOURCES = ("reference", "fast", "app")
#: Where the MathJax files land in the site (mkdocs.yml's extra_javascript names the entry).
MATHJAX_DEST = "javascripts/mathjax"
#: The one MathJax entry point the site uses; the other combined builds and the SVG output are
#: not copied.
MATHJAX_UNUSED = re.compile(r"^(?:(?!tex-chtml\.js$)[^/]+\.js$|output/svg/)")
#: The notebook template's MathJax 2 loader and configuration (MathJax 3 ignores both).
MATHJAX2_BLOCK = re.compile(r"<!-- Load mathjax -->.*?<!-- End of mathjax configuration -->", re.S)


@cache
def _sources_hash() -> str:
    h = hashlib.sha256()
    for folder in SOURCES:
        for path in sorted((ROOT / folder).rglob("*.py")):
            h.update(str(path.relative_to(ROOT)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def cache_key(tutorial: Path) -> str:
    return hashlib.sha256(tutorial.read_bytes() + _sources_hash().encode()).hexdigest()


def executed_notebook(tutorial: Path, nb=None) -> Path:
    """Path of the executed notebook of ``tutorial``; executes it unless cached (or given)."""
    import jupytext
    import nbformat

    out = CACHE / "tutorials" / f"{tutorial.stem}.ipynb"
    key = cache_key(tutorial)
    if nb is None and out.exists():
        old = nbformat.read(out, as_version=4)
        if old.metadata.get("mslam", {}).get("key") == key:
            return out
    if nb is None:
        from nbclient import NotebookClient

        nb = jupytext.read(tutorial)
        saved = os.environ.pop("MPLBACKEND", None)  # the kernel must use the inline backend
        try:
            with tempfile.TemporaryDirectory() as cwd:  # anything a tutorial writes lands here
                NotebookClient(
                    nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": cwd}}
                ).execute()
        finally:
            if saved is not None:
                os.environ["MPLBACKEND"] = saved
    nb.metadata["mslam"] = {"key": key, "source": f"tutorials/{tutorial.name}"}
    out.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, out)
    return out


def mathjax_dir() -> Path:
    """MathJax 3's ``es5`` folder inside the installed ``django-static-mathjax`` package."""
    spec = importlib.util.find_spec("mathjax")
    es5 = None
    if spec is not None and spec.submodule_search_locations:
        es5 = Path(next(iter(spec.submodule_search_locations))) / "static" / "mathjax" / "es5"
    if es5 is None or not (es5 / "tex-chtml.js").is_file():
        raise RuntimeError(
            "MathJax files not found: install the docs extra (pip install -e '.[docs]', which "
            "brings django-static-mathjax)"
        )
    return es5


def mathjax_files(es5: Path) -> list[str]:
    """Paths (relative to ``es5``) of the MathJax files the site serves."""
    rels = (p.relative_to(es5).as_posix() for p in sorted(es5.rglob("*")) if p.is_file())
    return [r for r in rels if not MATHJAX_UNUSED.match(r)]


try:
    from mkdocs.plugins import event_priority
except ImportError:  # imported by the tests without mkdocs installed

    def event_priority(_priority):
        return lambda f: f


@event_priority(100)  # before mkdocs-jupyter's on_files turns notebooks into pages
def on_files(files, config):
    from mkdocs.structure.files import File

    es5 = mathjax_dir()
    for rel in mathjax_files(es5):
        files.append(File.generated(config, f"{MATHJAX_DEST}/{rel}", abs_src_path=str(es5 / rel)))
    for tutorial in sorted(TUTORIALS.glob("[0-9][0-9]_*.py")):
        executed_notebook(tutorial)
        files.append(
            File(
                f"tutorials/{tutorial.stem}.ipynb",
                src_dir=str(CACHE),
                dest_dir=config["site_dir"],
                use_directory_urls=config["use_directory_urls"],
            )
        )
    return files


def on_post_page(output: str, page, config) -> str:
    """Drop the notebook template's dead MathJax 2 block from the tutorial pages."""
    return MATHJAX2_BLOCK.sub("", output)
