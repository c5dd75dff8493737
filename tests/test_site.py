"""The documentation site builds with ``mkdocs build --strict``, offline, and renders its maths.

Marked ``docs``: skipped when the site packages (the ``docs`` extra, part of ``dev``) are absent;
CI installs ``dev`` and runs it. The tutorials are executed through tools/mkdocs_hooks.py's
cache, which tests/test_notebooks.py fills earlier in the same pytest run, so the build itself
mostly renders. The site is built once per module.

Offline: where the kernel allows a private network namespace (``unshare -n``, as root), the
build runs in one with only the loopback device up, so a build step that downloads anything
fails. Every page's ``<script src>``, ``<link href>`` and ``<img src>`` must be a local path.

Rendering: tutorial 02 is opened in headless Chromium (``apt-get install chromium``; the test
skips without it), served by ``http.server`` on 127.0.0.1 with every other host unresolvable,
every file it asks for must be there (MathJax's fonts included), and the DOM after MathJax ran
must hold at least :data:`MIN_FORMULAS` typeset formulas and no raw TeX (``$...$``,
``\\(...\\)``) in its text.
"""

from __future__ import annotations

import functools
import http.server
import re
import shutil
import subprocess
import sys
import threading
from html.parser import HTMLParser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = sorted((ROOT / "tutorials").glob("[0-9][0-9]_*.py"))

#: Typeset formulas (``mjx-container`` elements) tutorial 02 must show (it has 41 inline spans).
MIN_FORMULAS = 10
#: Chromium's virtual-time budget for MathJax to load and typeset, milliseconds.
CHROMIUM_BUDGET_MS = 20000

pytestmark = pytest.mark.docs


def _offline_prefix() -> list[str]:
    """A command prefix running in a new network namespace with only loopback up, or [] where
    this kernel or user cannot create one."""
    if not (shutil.which("unshare") and shutil.which("ip")):
        return []
    prefix = ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$@"', "sh"]
    ok = subprocess.run([*prefix, "true"], capture_output=True, timeout=30).returncode == 0
    return prefix if ok else []


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    for module in ("mkdocs", "material", "mkdocs_jupyter", "mkdocstrings", "mathjax"):
        pytest.importorskip(module)
    out = tmp_path_factory.mktemp("site") / "site"
    build = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)]
    proc = subprocess.run(
        [*_offline_prefix(), *build],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return out


def test_site_builds_strict(site: Path) -> None:
    for path in TUTORIALS:
        page = site / "tutorials" / f"{path.stem}.html"
        assert page.exists(), f"no page for {path.name}"
        html = page.read_text()
        n = len(re.findall(r"<img[^>]+src=\"data:image/png", html))
        assert n >= 3, f"{page.name}: {n} inline figures"
        assert "What you will learn" in html and "Exercises" in html
        assert "MathJax.Hub" not in html, f"{page.name}: the dead MathJax 2 block is still there"
    for name in (
        "getting_started",
        "paper_map",
        "conventions",
        "architecture",
        "cli",
        "benchmarks",
    ):
        assert (site / f"{name}.html").exists(), name
    api = (site / "api" / "reference.html").read_text()
    assert "mslam_ref.sim3.retract" in api or "retract" in api
    assert (site / "javascripts" / "mathjax" / "tex-chtml.js").is_file()


class _Assets(HTMLParser):
    """``(tag, url)`` of every script src, link href and img src of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[tuple[str, str]] = []

    def handle_starttag(self, tag: str, attrs: list) -> None:
        key = {"script": "src", "link": "href", "img": "src"}.get(tag)
        value = dict(attrs).get(key) if key else None
        if value:
            self.urls.append((tag, value))


def remote_assets(html: str) -> list[tuple[str, str]]:
    """The assets of a page that a browser would fetch from another host."""
    parser = _Assets()
    parser.feed(html)
    return [(t, u) for t, u in parser.urls if re.match(r"^([a-z][a-z0-9+.-]*:)?//", u, re.I)]


def test_remote_asset_detection() -> None:
    page = (
        '<script src="https://cdn.example/x.js"></script><link rel="stylesheet" '
        'href="//fonts.example/css"><script src="../js/a.js"></script><img src="data:image/png;'
        'base64,AA"><link href="../a.css">'
    )
    assert remote_assets(page) == [
        ("script", "https://cdn.example/x.js"),
        ("link", "//fonts.example/css"),
    ]


def test_every_page_loads_only_local_assets(site: Path) -> None:
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 20
    bad = {str(p.relative_to(site)): remote_assets(p.read_text()) for p in pages}
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, bad


class _VisibleText(HTMLParser):
    """Text of a DOM outside code, scripts, styles and typeset maths; counts the formulas."""

    SKIP = frozenset({"code", "pre", "script", "style", "textarea", "mjx-container"})

    def __init__(self) -> None:
        super().__init__()
        self.depth = 0
        self.parts: list[str] = []
        self.formulas = 0

    def handle_starttag(self, tag: str, attrs: list) -> None:
        if tag == "mjx-container" and self.depth == 0:
            self.formulas += 1
        if tag in self.SKIP:
            self.depth += 1

    def handle_endtag(self, tag: str) -> None:
        if tag in self.SKIP and self.depth:
            self.depth -= 1

    def handle_data(self, data: str) -> None:
        if not self.depth:
            self.parts.append(data)


def raw_tex(dom: str) -> tuple[int, list[str]]:
    """(typeset formulas, raw TeX left in the visible text) of a rendered DOM."""
    parser = _VisibleText()
    parser.feed(dom)
    text = "".join(parser.parts)
    left = re.findall(r"\$[^$\n]{1,80}\$|\\\(.{1,80}?\\\)|\\\[.{1,80}?\\\]", text, re.S)
    return parser.formulas, left


def test_raw_tex_detection() -> None:
    dom = (
        "<p>see $T_{12}$ and \\(x\\)</p><mjx-container><mjx-math>$y$</mjx-math></mjx-container>"
        "<pre>echo $HOME $PATH</pre><p>costs 5 dollars</p>"
    )
    formulas, left = raw_tex(dom)
    assert formulas == 1 and left == ["$T_{12}$", "\\(x\\)"]


@functools.cache
def _chromium() -> str | None:
    return next((p for p in map(shutil.which, ("chromium", "chromium-browser")) if p), None)


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Serves the site quietly and records ``(path, status)`` of every request."""

    requests: list[tuple[str, int]]

    def log_request(self, code="-", size="-") -> None:
        self.requests.append((self.path, int(code)))

    def log_message(self, *args) -> None:
        pass


def _render(site: Path, page: str, tmp_path: Path) -> str:
    """The DOM of ``page`` after its scripts ran in headless Chromium, served from 127.0.0.1;
    fails if the page asked the server for a file it does not have."""
    requests: list[tuple[str, int]] = []
    handler = type("Handler", (_Handler,), {"requests": requests})
    handler = functools.partial(handler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        proc = subprocess.run(
            [
                _chromium(),
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                f"--user-data-dir={tmp_path / 'chromium'}",
                "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
                f"--virtual-time-budget={CHROMIUM_BUDGET_MS}",
                "--dump-dom",
                f"http://127.0.0.1:{server.server_address[1]}/{page}",
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
    finally:
        server.shutdown()
        server.server_close()
    assert proc.returncode == 0 and "</html>" in proc.stdout, proc.stderr[-2000:]
    missing = [r for r in requests if r[1] >= 400]
    assert not missing, f"{page}: requests that failed: {missing}"
    assert any(path.endswith(".woff") for path, _ in requests), "no MathJax font was loaded"
    return proc.stdout


@pytest.mark.parametrize(
    "page, min_formulas",
    [("tutorials/02_matching.html", MIN_FORMULAS), ("matching.html", 1)],
)
def test_maths_is_typeset_in_chromium(site: Path, tmp_path: Path, page, min_formulas) -> None:
    """Tutorial 02 ($...$ in Markdown cells) and a design page (pymdownx.arithmatex)."""
    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium)")
    formulas, left = raw_tex(_render(site, page, tmp_path))
    assert not left, f"{page}: raw TeX in the rendered text: {left[:5]}"
    assert formulas >= min_formulas, f"{page}: {formulas} typeset formulas"
