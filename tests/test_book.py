"""The online book: book.yml checks (fast), then a real build read in headless Chromium.

CI's build renders the notebooks without running them: nbval has run every one
of them at ci scale already (`make test`), so running them here would be twice.
"""

from __future__ import annotations

import functools
import http.server
import json
import re
import shutil
import subprocess
import threading
from html import escape as html_escape
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urljoin, urlparse

import pytest
from PIL import Image, ImageStat

from tools import book as bk

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
BROWSER_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 # no host names resolve, so a page that needs the web fails here too
                 "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1")


def write_book(tmp_path: Path, text: str, chapters=("notebooks/00_a.ipynb",)) -> Path:
    """A book.yml in ``tmp_path`` with empty chapter files; return its path."""
    for chapter in chapters:
        (tmp_path / chapter).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / chapter).write_text("{}")
    path = tmp_path / "book.yml"
    path.write_text(text)
    return path


def test_load_book_reads_every_setting(tmp_path):
    path = write_book(tmp_path, "title: T\nauthors: Ada\nchapters: [notebooks/00_a.ipynb]\n"
                                "execute: {scale: ci, cache: false, timeout: 60, "
                                "long_timeout: 600}\n")
    book = bk.load_book(path)
    assert (book.title, book.authors, book.chapters) == ("T", ("Ada",), ("notebooks/00_a.ipynb",))
    assert (book.scale, book.cache, book.timeout, book.long_timeout, book.root) == (
        "ci", False, 60, 600, tmp_path)


@pytest.mark.parametrize("text, problem", [
    ("title: T\nchapters: [notebooks/00_a.ipynb]\ncolour: red\n", "unknown keys"),
    ("title: T\nchapters: [notebooks/09_missing.ipynb]\n", "does not exist"),
    ("title: T\nchapters: [../outside.ipynb]\n", "inside"),
    ("title: T\nchapters: [notebooks/00_a.ipynb]\nexecute: {scale: huge}\n", "not one of"),
    ("chapters: [notebooks/00_a.ipynb]\n", "needs a `title`"),
])
def test_load_book_names_the_problem(tmp_path, text, problem):
    with pytest.raises(bk.BookError, match=problem):
        bk.load_book(write_book(tmp_path, text))


def test_scale_comes_from_flag_then_environment_then_book(tmp_path):
    book = bk.load_book(write_book(tmp_path, "title: T\nchapters: [notebooks/00_a.ipynb]\n"
                                             "execute: {scale: full}\n"))
    assert bk.resolve_scale(book, None, {}) == "full"
    assert bk.resolve_scale(book, None, {"EBJEPA_SCALE": "CI"}) == "ci"
    assert bk.resolve_scale(book, "class", {"EBJEPA_SCALE": "ci"}) == "class"
    with pytest.raises(bk.BookError, match="not one of"):
        bk.resolve_scale(book, None, {"EBJEPA_SCALE": "tiny"})


def test_generated_project_is_offline_and_lists_chapters(tmp_path):
    chapters = ("notebooks/00_a.ipynb", "notebooks/01_b.ipynb")
    book = bk.load_book(write_book(tmp_path, "title: My Book\nchapters: [notebooks/00_a.ipynb, "
                                             "notebooks/01_b.ipynb]\n", chapters))
    conf = bk.conf_py(book)
    assert "mathjax_path = 'mathjax/MathJax.js'" in conf and "http" not in conf
    assert "nb_execution_mode = 'off'" in conf  # execute_notebook runs them, with time limits
    index = bk.index_md(book, "ci")
    assert index.startswith("# My Book") and "`ci`" in index
    assert index.index("notebooks/00_a\n") < index.index("notebooks/01_b\n")
    assert "solutions edition" in index and "make lab-student" in index  # learners: the stubs


def test_the_courses_book_holds_every_notebook_in_order():
    book = bk.load_book(Path(__file__).resolve().parents[1] / "book.yml")
    notebooks = sorted(p for p in book.chapters if p.startswith("notebooks/"))
    on_disk = sorted(f"notebooks/{p.name}" for p in (book.root / "notebooks").glob("*.ipynb"))
    assert notebooks == on_disk and list(notebooks) == [
        p for p in book.chapters if p.startswith("notebooks/")]  # a new chapter is not left out


def tiny_notebook(tmp_path: Path, *cells: tuple[str, list[str]]) -> Path:
    """A notebook of code cells (source, tags) in ``tmp_path``; return its path."""
    import nbformat  # here: its validator takes seconds to import, and only slow tests run it

    notebook = nbformat.v4.new_notebook()
    notebook.cells = [nbformat.v4.new_code_cell(source, metadata={"tags": tags})
                      for source, tags in cells]
    notebook.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3"}
    path = tmp_path / "07_tiny.ipynb"
    nbformat.write(notebook, path)
    return path


def quick_book(tmp_path: Path, timeout: int = 60, long_timeout: int = 60) -> bk.Book:
    return bk.Book(root=tmp_path, title="T", authors=(), chapters=("07_tiny.ipynb",),
                   timeout=timeout, long_timeout=long_timeout)


@pytest.mark.slow
@pytest.mark.parametrize("failing, named", [
    ("x = 1 / 0", "with ZeroDivisionError: division by zero"),
    ("import os\nos._exit(1)  # the kernel dies", "Its kernel died"),
])
def test_failed_cell_is_named_with_its_notebook(tmp_path, failing, named):
    path = tiny_notebook(tmp_path, ("import os\nscale = os.environ['EBJEPA_SCALE']", []),
                         (failing, []), ("never_runs = True", []))
    with pytest.raises(bk.BookError) as raised:
        bk.execute_notebook(path, tmp_path / "out.ipynb", quick_book(tmp_path), "ci")
    message = str(raised.value)
    assert "notebook 07_tiny.ipynb" in message and "in its cell 1" in message
    assert failing.splitlines()[0] in message and named in message
    assert not (tmp_path / "out.ipynb").exists()


@pytest.mark.slow
def test_long_running_cells_get_their_own_time_limit(tmp_path, monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    book = quick_book(tmp_path, timeout=1, long_timeout=60)
    path = tiny_notebook(tmp_path, ("import os, time\ntime.sleep(3)\n"
                                    "print(os.environ['OMP_WAIT_POLICY'])", [bk.LONG_TAG]))
    bk.execute_notebook(path, tmp_path / "out.ipynb", book, "ci")
    executed = json.loads((tmp_path / "out.ipynb").read_text())
    output = "".join(executed["cells"][0]["outputs"][0]["text"])
    assert output == "PASSIVE\n"  # waiting threads sleep

    path = tiny_notebook(tmp_path, ("import time\ntime.sleep(3)", []))
    with pytest.raises(bk.BookError, match="past its limit of 1 s.*tag the cell 'long-running'"):
        bk.execute_notebook(path, tmp_path / "out.ipynb", book, "ci")


@pytest.mark.slow
def test_the_book_shows_no_progress_bar_frozen_at_zero(tmp_path):
    path = tiny_notebook(tmp_path, ("from tqdm.auto import tqdm\n"
                                    "total = sum(tqdm(range(3), desc='steps'))\nprint(total)", []))
    import nbformat

    notebook = nbformat.read(path, as_version=4)
    notebook.cells.insert(0, nbformat.v4.new_markdown_cell("A title"))
    nbformat.write(notebook, path)
    bk.execute_notebook(path, tmp_path / "out.ipynb", quick_book(tmp_path), "ci")
    executed = nbformat.read(tmp_path / "out.ipynb", as_version=4)
    nbformat.validate(executed)  # the markdown cell got no outputs of its own
    assert [o.get("text") for o in executed.cells[1].outputs] == ["3\n"]  # no widget, no bar


@pytest.mark.slow
def test_the_book_draws_figures_whatever_backend_the_shell_sets(tmp_path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "agg")  # as `make test` sets it
    path = tiny_notebook(tmp_path, ("import matplotlib.pyplot as plt\nplt.plot([0, 1])\n"
                                    "plt.show()", []))
    bk.execute_notebook(path, tmp_path / "out.ipynb", quick_book(tmp_path), "ci")
    outputs = json.loads((tmp_path / "out.ipynb").read_text())["cells"][0]["outputs"]
    assert any("image/png" in o.get("data", {}) for o in outputs)


LONG_CALLS = re.compile(r"(?<!def )train_or_load\(|probe_encoder\(|run_episodes\(|"
                        r"probe_report\(")


def test_a_cached_run_is_reused_only_while_what_it_shows_is_unchanged(tmp_path, monkeypatch):
    reference = tmp_path / "reference.json"
    reference.write_text("{}")
    monkeypatch.setattr(bk, "REFERENCE_FILE", reference)
    path = tmp_path / "00_x.ipynb"

    def key(markdown="Some prose.", code="x = 1"):
        cells = [{"cell_type": "markdown", "metadata": {}, "source": markdown},
                 {"cell_type": "code", "metadata": {}, "outputs": [], "source": code.splitlines(
                     keepends=True)}]  # a notebook may store a source as its lines
        path.write_text(json.dumps({"cells": cells, "metadata": {}, "nbformat": 4,
                                    "nbformat_minor": 5}))
        return bk.notebook_key(path, "ci")

    first = key()
    assert key() == first and key(code="x = 2") != first
    assert key(markdown="Other prose.") != first  # the cached copy holds the prose too
    reference.write_text('{"a": 1}')  # a new recorded figure, printed beside the learner's
    assert key() != first


def test_cached_outputs_expire_when_the_runner_changes(monkeypatch):
    before = bk.package_fingerprint()

    def execute_notebook(path, target, book, scale):  # a runner that keeps other outputs
        raise AssertionError("not called")

    monkeypatch.setattr(bk, "execute_notebook", execute_notebook)
    assert bk.package_fingerprint() != before


def test_a_link_to_a_file_the_book_does_not_hold_names_the_file():
    book = bk.load_book(bk.DEFAULT_CONFIG)
    text = ("the [notes](../research/notes/log.md#one), [results](../RESULTS.md), "
            "[a site](https://example.org/x.md), [above](#top) and ![a picture](p.png)")
    assert bk.outside_links(text, "notebooks/01_vicreg.ipynb", book) == (
        "the notes (`research/notes/log.md` in the course's repository), "
        "[results](../RESULTS.md), [a site](https://example.org/x.md), [above](#top) and "
        "![a picture](p.png)")


def test_cells_that_train_or_play_are_tagged_long_running():
    """Training, probes and episodes take minutes at class scale, several times that on busy
    cores: the book gives them execute.long_timeout instead of the per-cell timeout."""
    untagged = []
    for path in sorted((bk.DEFAULT_CONFIG.parent / "notebooks").glob("*.ipynb")):
        for index, cell in enumerate(json.loads(path.read_text(encoding="utf-8"))["cells"]):
            if (cell["cell_type"] == "code" and LONG_CALLS.search("".join(cell["source"]))
                    and bk.LONG_TAG not in cell["metadata"].get("tags", ())):
                untagged.append(f"{path.name} cell {index}")
    assert not untagged, f"tag these cells {bk.LONG_TAG!r}: {untagged}"


# ---- the real book, built at ci scale and opened in a browser (slow) ----


class LinkCollector(HTMLParser):
    """Collects the hrefs of links inside the sidebar's chapter navigation."""

    def __init__(self):
        super().__init__()
        self.depth, self.links = 0, []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "nav" and "bd-docs-nav" in (attrs.get("class") or ""):
            self.depth = 1
        elif tag == "nav" and self.depth:
            self.depth += 1
        elif tag == "a" and self.depth:
            self.links.append(attrs.get("href", ""))

    def handle_endtag(self, tag):
        if tag == "nav" and self.depth:
            self.depth -= 1


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    """Serves the built site without logging every request."""

    def log_message(self, *args):
        pass


def find_browser() -> str:
    for name in BROWSERS:
        if path := shutil.which(name):
            return path
    pytest.skip("no headless Chromium found: install one (Debian: `apt-get install chromium`) "
                "to read the built book in a browser")


def run_browser(url: str, profile: Path, *args: str) -> str:
    """Open ``url`` in headless Chromium, let scripts run 10 s of virtual time; return stdout."""
    command = [find_browser(), *BROWSER_FLAGS, f"--user-data-dir={profile}",
               "--virtual-time-budget=10000", *args, url]
    result = subprocess.run(command, capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """Build the book described by the repository's book.yml, unexecuted; serve it locally."""
    work = tmp_path_factory.mktemp("book")
    html = bk.build_book(bk.DEFAULT_CONFIG, scale="ci", work=work, execute=False)
    handler = functools.partial(QuietHandler, directory=str(html))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)  # a free port
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield bk.load_book(bk.DEFAULT_CONFIG), html, f"http://127.0.0.1:{server.server_port}/", work
    server.shutdown()


@pytest.mark.slow
def test_no_link_in_the_book_points_at_a_page_it_does_not_hold(site):
    _, html, _, _ = site
    dead = [(page.name, href) for page in html.rglob("*.html")
            for href in re.findall(r'href="(#[^"]*[./][^"]*)"', page.read_text())]
    assert not dead, f"links to nowhere (a file outside the book?): {dead[:5]}"


@pytest.mark.slow
def test_site_loads_nothing_from_the_network(site):
    _, html, _, _ = site
    assert (html / "_static" / "mathjax" / "MathJax.js").is_file()
    assert bk.find_external_assets(html) == []


@pytest.mark.slow
@pytest.mark.browser
def test_index_shows_title_and_chapter_navigation(site):
    book, _, url, work = site
    dom = run_browser(url + "index.html", work / "profile-index", "--dump-dom")
    title = html_escape(book.title, quote=False)
    assert f"<title>{title}" in dom
    assert re.search(rf"<h1[^>]*>\s*{re.escape(title)}\s*<", dom), "no title heading"
    nav = LinkCollector()
    nav.feed(dom)
    pages = [urlparse(urljoin(url, href)).path.lstrip("/") for href in nav.links]
    for chapter in book.chapters:
        assert str(Path(chapter).with_suffix(".html")) in pages, (chapter, pages)


@pytest.mark.slow
@pytest.mark.browser
def test_first_chapter_renders_math_and_code(site):
    book, html, url, work = site
    page = str(Path(book.chapters[0]).with_suffix(".html"))
    dom = run_browser(url + page, work / "profile-dom", "--dump-dom")
    assert "<title>" in dom and "bd-docs-nav" in dom
    assert re.search(r'class="MathJax(_Display)?"', dom), "MathJax rendered no math"
    visible = re.sub(r"<script\b.*?</script>", "", dom, flags=re.S)
    assert "\\(" not in visible and "\\[" not in visible, "raw TeX left on the page"
    assert "Math Processing Error" not in visible
    assert "shown as committed, without outputs" in (html / "index.html").read_text()
    assert 'class="cell_input' in dom, "no code cell rendered on the page"

    shot = work / "chapter-00.png"
    run_browser(url + page, work / "profile-shot", f"--screenshot={shot}",
                "--window-size=1280,2000", "--hide-scrollbars")
    with Image.open(shot) as picture:
        assert picture.size == (1280, 2000)
        assert max(ImageStat.Stat(picture.convert("L")).stddev) > 10, "blank screenshot"
    print(f"screenshot of {page}: {shot}")


@pytest.mark.parametrize("cell", [
    {"cell_type": "markdown", "metadata": {}, "source": "<!--BEGIN SOLUTION-->the answer"},
    {"cell_type": "markdown", "metadata": {}, "source": "<!-- BEGIN SOLUTION -->no end"},
    {"cell_type": "raw", "metadata": {}, "source": "### BEGIN SOLUTION\nx = 1\n### END SOLUTION"},
    {"cell_type": "code", "metadata": {}, "outputs": [], "execution_count": None,
     "source": "def f(x):\n    ## begin solution\n    return x\n"},
])
def test_a_misspelt_solution_marker_stops_the_student_build(cell):
    from tools.student import student_notebook

    notebook = {"cells": [cell], "metadata": {}, "nbformat": 4, "nbformat_minor": 5}
    with pytest.raises(ValueError, match="solution marker is left"):
        student_notebook(notebook)
