"""Build the course's online book from ``book.yml``, fully offline.

    python -m tools.book build [--scale ci|class|full] [--no-execute]
                               [--out DIR] [--config FILE]

``book.yml`` names the title, authors, chapters (notebooks, in order) and how
to execute them. ``build`` executes every notebook at the chosen scale in its own
folder, writes a Sphinx project into ``build/book-src`` (generated ``conf.py`` and
title page, the executed chapters, a local MathJax), then runs sphinx-build, which
renders them (myst-nb) into ``build/book/html``. Nothing comes from the network.
``--no-execute`` renders the notebooks as committed, without outputs: CI does
that, since nbval has already run every notebook there.

Executed notebooks are cached in ``build/book-cache`` per scale, per notebook text
and per version of the package's code, so a second build is fast. A cell may run
``execute.timeout`` seconds; a cell tagged ``long-running`` (training, probes,
episodes: minutes when the cores are idle, several times that when they are
shared) may run ``execute.long_timeout``. A kernel that dies fails the build at
once, naming the notebook and the cell.
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

from ebjepa_tutorial.course.presets import SCALES
from ebjepa_tutorial.course.reference import REFERENCE_FILE

ROOT = Path(__file__).resolve().parents[1]  # the repository
PACKAGE_DIR = ROOT / "ebjepa_tutorial"
DEFAULT_CONFIG = ROOT / "book.yml"
MATHJAX_DIR = "mathjax"  # under _static/
WIDGET = "application/vnd.jupyter.widget-view+json"  # an output that needs the widget JavaScript
BOOK_KEYS = {"title", "subtitle", "authors", "description", "chapters", "execute"}
EXECUTE_KEYS = {"scale", "cache", "timeout", "long_timeout"}
LONG_TAG = "long-running"  # cells that train, probe or play episodes


class BookError(RuntimeError):
    """A problem with book.yml or the build, with a message that says how to fix it."""


@dataclass(frozen=True)
class Book:
    """What ``book.yml`` says; chapter paths are relative to ``root`` (book.yml's folder)."""

    root: Path
    title: str
    authors: tuple[str, ...]
    chapters: tuple[str, ...]
    subtitle: str = ""
    description: str = ""
    scale: str = "class"
    cache: bool = True
    timeout: int = 1800  # seconds per cell
    long_timeout: int = 4 * 3600  # seconds per cell tagged LONG_TAG


def load_book(path: str | Path = DEFAULT_CONFIG) -> Book:
    """Read and check ``book.yml``; raise BookError naming the bad entry."""
    path = Path(path).resolve()
    if not path.is_file():
        raise BookError(f"no book description at {path}; pass --config PATH/book.yml")
    raw = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    execute = raw.get("execute") or {}
    for where, keys, known in (("", raw, BOOK_KEYS), ("execute ", execute, EXECUTE_KEYS)):
        if set(keys) - known:
            raise BookError(f"{path.name}: unknown {where}keys {sorted(set(keys) - known)}; "
                            f"known: {sorted(known)}")
    if not raw.get("title") or not raw.get("chapters"):
        raise BookError(f"{path.name} needs a `title` and a non-empty `chapters` list")
    authors = raw.get("authors") or []
    authors = (authors,) if isinstance(authors, str) else tuple(authors)
    book = Book(root=path.parent, title=str(raw["title"]), authors=authors,
                chapters=tuple(str(c) for c in raw["chapters"]),
                subtitle=str(raw.get("subtitle") or ""),
                description=str(raw.get("description") or ""),
                scale=str(execute.get("scale", "class")), cache=bool(execute.get("cache", True)),
                timeout=int(execute.get("timeout", 1800)),
                long_timeout=int(execute.get("long_timeout", 4 * 3600)))
    check_book(book, path.name)
    return book


def check_book(book: Book, name: str = "book.yml") -> None:
    """Raise BookError if a chapter is missing or outside the book, or a setting is invalid."""
    if book.scale not in SCALES:
        raise BookError(f"{name}: execute.scale {book.scale!r} is not one of {SCALES}")
    if min(book.timeout, book.long_timeout) <= 0:
        raise BookError(f"{name}: execute.timeout and execute.long_timeout must be positive "
                        f"numbers of seconds")
    for chapter in book.chapters:
        rel = Path(chapter)
        if rel.is_absolute() or ".." in rel.parts or rel.suffix not in (".ipynb", ".md"):
            raise BookError(f"{name}: chapter {chapter!r} must be a .ipynb or .md path "
                            f"inside {book.root}, relative to {name}")
        if not (book.root / rel).is_file():
            raise BookError(f"{name} lists chapter {chapter!r}, but {book.root / rel} does not "
                            f"exist; fix the path or remove the chapter from {name}")


def resolve_scale(book: Book, scale: str | None = None, environ=None) -> str:
    """The scale to execute at: ``--scale``, else ``EBJEPA_SCALE``, else book.yml."""
    environ = os.environ if environ is None else environ
    chosen = scale or environ.get("EBJEPA_SCALE", "").strip().lower() or book.scale
    if chosen not in SCALES:
        raise BookError(f"scale {chosen!r} is not one of {SCALES} (from --scale or EBJEPA_SCALE)")
    return chosen


def package_fingerprint() -> str:
    """A short hash of the package's Python sources, which notebooks run, and of the runner
    (:func:`execute_notebook`), which sets what their outputs hold."""
    digest = hashlib.sha256(inspect.getsource(execute_notebook).encode())
    for file in sorted(PACKAGE_DIR.rglob("*.py")):
        digest.update(file.relative_to(PACKAGE_DIR).as_posix().encode())
        digest.update(file.read_bytes())
    return digest.hexdigest()[:12]


def mathjax_config() -> dict:
    """MathJax 2 settings: the bundled TeX config, and the STIX web fonts that ship with it."""
    return {
        "config": ["TeX-AMS-MML_HTMLorMML-full.js"],
        "tex2jax": {"inlineMath": [["\\(", "\\)"]], "displayMath": [["\\[", "\\]"]],
                    "processEscapes": True},
        # jupyter-server-mathjax ships only the STIX-Web fonts, so ask for exactly those.
        "HTML-CSS": {"availableFonts": [], "preferredFont": None, "webFont": "STIX-Web",
                     "imageFont": None},
        "SVG": {"font": "STIX-Web"},
        "messageStyle": "none",
    }


def conf_py(book: Book) -> str:
    """The text of the generated Sphinx ``conf.py``."""
    settings = {
        "project": book.title,
        "author": ", ".join(book.authors),
        "extensions": ["myst_nb", "sphinx.ext.mathjax"],
        "root_doc": "index",
        "include_patterns": ["index.md", *book.chapters],
        "exclude_patterns": ["**/.ipynb_checkpoints"],
        "myst_enable_extensions": ["dollarmath", "amsmath"],
        "myst_update_mathjax": False,  # it writes MathJax 3+ settings; we serve MathJax 2
        "mathjax_path": f"{MATHJAX_DIR}/MathJax.js",  # relative to _static: served locally
        "mathjax2_config": mathjax_config(),
        "nb_execution_mode": "off",  # execute_notebook ran them, with per-cell time limits
        "nb_merge_streams": True,
        "nb_ipywidgets_js": {},  # the default loads require.js and widgets from CDNs
        "html_theme": "sphinx_book_theme",
        "html_title": book.title,
        "html_static_path": ["_static"],
        "html_show_copyright": False,  # the footer already says "By <authors>"
        "html_theme_options": {
            "home_page_in_toc": True, "show_toc_level": 2, "use_download_button": True,
            # off: everything that links to a repository or launches Binder/Colab online
            "use_repository_button": False, "use_issues_button": False,
            "use_source_button": False, "launch_buttons": {},
            "navbar_persistent": [],  # else a second search box sits in an empty top bar
        },
    }
    lines = ["# Generated by `python -m tools.book build` from book.yml; "
             "edits are lost."]
    lines += [f"{key} = {value!r}" for key, value in settings.items()]
    return "\n".join(lines) + "\n"


def index_md(book: Book, scale: str | None) -> str:
    """The title page: title, authors, description, the scale it was run at, the chapters."""
    docs = [str(Path(chapter).with_suffix("").as_posix()) for chapter in book.chapters]
    parts = [f"# {book.title}", ""]
    if book.subtitle:
        parts += [f"*{book.subtitle}*", ""]
    if book.authors:
        parts += ["By " + ", ".join(book.authors), ""]
    if book.description:
        parts += [book.description.strip(), ""]
    parts += ["This is the solutions edition: every exercise is shown solved. To work them "
              "yourself, open the student versions with `make lab-student`.", ""]
    if scale is None:
        parts += ["The notebooks on these pages are shown as committed, without outputs: "
                  "run them with `make lab`.", ""]
    else:
        parts += [f"The notebooks on these pages were executed at scale `{scale}` "
                  f"(`EBJEPA_SCALE={scale}`). Progress bars and interactive widgets appear "
                  "only when you run a notebook in Jupyter.", ""]
    parts += ["```{toctree}", ":caption: Chapters", ":maxdepth: 1", "", *docs, "```", ""]
    return "\n".join(parts)


LINK = re.compile(r"(?<!!)\[([^\]]+)\]\(([^)\s]+)\)")  # [text](target), not an image


def outside_links(text: str, page: str, book: Book) -> str:
    """``text`` of the book page ``page`` (its path in the repository) with each link to a
    repository file that is not a page of the book (a maintainers' note, a README beside
    the code) written as its text and the file's path: the book does not hold that file."""
    def rewrite(match: re.Match) -> str:
        words, target = match.groups()
        if re.match(r"[a-z]+:|#", target):  # a web address or an anchor on this page
            return match.group(0)
        path = os.path.normpath((Path(page).parent / target.split("#")[0]).as_posix())
        if Path(path).as_posix() in book.chapters:
            return match.group(0)
        return f"{words} (`{Path(path).as_posix()}` in the course's repository)"

    return LINK.sub(rewrite, text)


def write_sphinx_project(book: Book, scale: str | None, src: Path,
                         executed: dict[str, Path]) -> None:
    """Fill ``src`` with conf.py, index.md, the chapters' folders (``executed`` maps a
    notebook chapter to its executed copy) and MathJax in _static."""
    src.mkdir(parents=True, exist_ok=True)
    for entry in src.iterdir():  # start clean, but keep the (large, unchanging) _static copy
        if entry.name == "_static":
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()
    (src / "conf.py").write_text(conf_py(book), encoding="utf-8")
    (src / "index.md").write_text(index_md(book, scale), encoding="utf-8")
    for top in sorted({Path(chapter).parts[0] for chapter in book.chapters}):
        source = book.root / top
        copy = shutil.copytree if source.is_dir() else shutil.copy2
        copy(source, src / top)  # pages are copied: Sphinx resolves links from where a file is
    for chapter, notebook in executed.items():
        shutil.copy2(notebook, src / chapter)
    for chapter in book.chapters:  # links to files the book does not hold name the file
        page = src / chapter
        if page.suffix == ".md":
            page.write_text(outside_links(page.read_text(encoding="utf-8"), chapter, book),
                            encoding="utf-8")
        else:
            import nbformat  # here: its validator takes seconds to import; only a build needs it

            notebook = nbformat.read(page, as_version=4)
            for cell in notebook.cells:
                if cell.cell_type == "markdown":
                    cell.source = outside_links(cell.source, chapter, book)
            nbformat.write(notebook, page)
    copy_mathjax(src / "_static" / MATHJAX_DIR)


def copy_mathjax(target: Path) -> None:
    """Copy MathJax 2 from the jupyter-server-mathjax package (once per build folder)."""
    try:
        import jupyter_server_mathjax
    except ImportError as error:
        raise BookError("jupyter-server-mathjax is missing; run `make setup` "
                        "(it is in the `book` extra of pyproject.toml)") from error
    source = Path(jupyter_server_mathjax.__file__).parent / "static"
    if not (target / "MathJax.js").is_file():  # 12 MB; the copy is kept between builds
        shutil.copytree(source, target, dirs_exist_ok=True)


def is_noise(line: str) -> bool:
    """Lines that say nothing to a reader: a warning about the local kernel, config dumps."""
    return "Kernel is running over TCP without encryption" in line or line.startswith(
        ("myst v", "myst-nb v"))


def notebook_key(path: Path, scale: str) -> str:
    """What an executed notebook shows: its cells (the prose too, which the cached copy holds),
    the scale, the package's code and the recorded figures its cells print beside yours."""
    digest = hashlib.sha256(f"{scale} {package_fingerprint()}".encode())
    for cell in json.loads(path.read_text(encoding="utf-8"))["cells"]:
        source = "".join(cell["source"])  # stored as one string or as its lines
        digest.update(f"{cell['cell_type']}\0{source}\0".encode())
    if REFERENCE_FILE.is_file():
        digest.update(REFERENCE_FILE.read_bytes())
    return f"{path.stem}-{digest.hexdigest()[:12]}"


def execute_notebook(path: Path, target: Path, book: Book, scale: str) -> None:
    """Run the notebook at ``path`` in its own folder at ``scale``; write it, with its outputs,
    to ``target``. Raise BookError naming the notebook and the cell if a cell fails, runs
    out of time or its kernel dies."""
    import nbformat
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError, CellTimeoutError, DeadKernelError

    notebook = nbformat.read(path, as_version=4)
    running = {}

    def note_cell(cell, cell_index, **_):
        running.update(cell=cell, index=cell_index)

    def time_limit(cell):
        return book.long_timeout if LONG_TAG in cell.metadata.get("tags", ()) else book.timeout

    client = NotebookClient(notebook, timeout_func=time_limit, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}},
                            on_cell_start=note_cell)
    # OpenMP threads that wait sleep instead of spinning: on cores shared with other jobs,
    # spinning threads of two torch processes slowed each other several-fold (RESULTS.md)
    # MPLBACKEND: the inline backend, as in Jupyter; an inherited "agg" (set for the tests)
    # would draw every figure off the page
    env = dict(os.environ, EBJEPA_SCALE=scale, PYDEVD_DISABLE_FILE_VALIDATION="1",
               OMP_WAIT_POLICY=os.environ.get("OMP_WAIT_POLICY", "PASSIVE"),
               MPLBACKEND="module://matplotlib_inline.backend_inline")
    try:
        client.execute(env=env)
    except (CellExecutionError, CellTimeoutError, DeadKernelError) as error:
        raise BookError(describe_failure(path.name, running, error, scale, book)) from None
    # the book loads no widget JavaScript: a widget would show its text fallback, saved in its
    # first state (a progress bar at 0%); only code cells have outputs
    for cell in (c for c in notebook.cells if c.cell_type == "code"):
        cell.outputs = [o for o in cell.outputs if WIDGET not in o.get("data", {})]
    target.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(notebook, target)


def describe_failure(name: str, running: dict, error: Exception, scale: str, book: Book) -> str:
    """One message for a notebook that did not run: which notebook, which cell, what error."""
    from nbclient.exceptions import CellTimeoutError, DeadKernelError

    message = f"notebook {name} failed while executing at scale {scale}"
    cell = running.get("cell")
    if cell is not None:
        source = cell.source.strip().splitlines()
        shown = "\n    ".join(source[:12] + (["..."] if len(source) > 12 else []))
        message += (f" in its cell {running['index']} (from 0, markdown cells counted):"
                    f"\n\n    {shown}\n")
    if isinstance(error, DeadKernelError):
        message += "\nIts kernel died (out of memory, or killed): nothing after this cell ran.\n"
    elif isinstance(error, CellTimeoutError):
        tagged = cell is not None and LONG_TAG in cell.metadata.get("tags", ())
        limit, key = (book.long_timeout, "long_timeout") if tagged else (book.timeout, "timeout")
        message += (f"\nThe cell ran past its limit of {limit} s. If it is only slow (cores "
                    f"shared with other jobs), raise execute.{key} in book.yml"
                    + ("" if tagged else f" or tag the cell {LONG_TAG!r}") + ".\n")
    else:
        message += f"\nwith {error.ename}: {error.evalue}\n"
    return message + (f"\nReproduce it with `EBJEPA_SCALE={scale} make lab`, fix the notebook "
                      f"or the package, then build again.")


def execute_chapters(book: Book, scale: str, cache_dir: Path) -> dict[str, Path]:
    """Execute every notebook chapter (or take it from ``cache_dir``); map each to its copy."""
    executed = {}
    for chapter in book.chapters:
        path = book.root / chapter
        if path.suffix != ".ipynb":
            continue
        done = cache_dir / f"{notebook_key(path, scale)}.ipynb"
        if not done.is_file():
            print(f"executing {chapter} at scale {scale} ...", flush=True)
            start = time.monotonic()
            execute_notebook(path, done.with_suffix(".running"), book, scale)
            done.with_suffix(".running").replace(done)  # cached only once it ran to the end
            print(f"    {chapter}: {(time.monotonic() - start) / 60:.1f} min", flush=True)
        executed[chapter] = done
    return executed


def run_sphinx(src: Path, out: Path, doctrees: Path) -> None:
    """Run sphinx-build on the executed chapters; raise BookError if it fails."""
    command = [sys.executable, "-m", "sphinx", "-b", "html", "-E", "-q", "-d", str(doctrees),
               str(src), str(out)]
    result = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = [line for line in result.stdout.splitlines() if not is_noise(line)]
    print("\n".join(lines), flush=True)
    if result.returncode != 0:
        raise BookError(f"sphinx-build failed with exit code {result.returncode} (messages above)")


def find_external_assets(html_dir: str | Path) -> list[tuple[str, str]]:
    """(file, url) for every script, stylesheet, font or image the site loads from the web."""
    tag = re.compile(r"<(?:script|link|img|iframe)\b[^>]*?\b(?:src|href)=[\"']"
                     r"((?:https?:)?//[^\"']+)", re.I)
    css_url = re.compile(r"(?:url\(|@import\s+)[\"']?((?:https?:)?//[^\"')\s]+)", re.I)
    found = []
    for file in sorted(Path(html_dir).rglob("*")):
        if file.suffix not in (".html", ".css") or MATHJAX_DIR in file.parts:
            continue
        text = file.read_text(encoding="utf-8", errors="replace")
        for match in (tag if file.suffix == ".html" else css_url).finditer(text):
            if file.suffix == ".html" and "<link" in match.group(0).lower():
                rel = re.search(r"rel=[\"']([^\"']+)", match.group(0))
                if rel and rel.group(1) not in ("stylesheet", "preload", "icon", "modulepreload"):
                    continue  # plain hyperlinks are fine; only assets must be local
            found.append((str(file.relative_to(html_dir)), match.group(1)))
    return found


def build_book(config: str | Path = DEFAULT_CONFIG, scale: str | None = None,
               out: str | Path | None = None, work: str | Path | None = None,
               execute: bool = True) -> Path:
    """Build the HTML book; return the folder with ``index.html``.

    ``work`` holds the generated Sphinx project and the execution cache
    (default: ``build/`` next to book.yml); ``out`` defaults to ``work/book/html``.
    ``execute=False`` renders the notebooks as committed, without outputs.
    """
    book = load_book(config)
    scale = resolve_scale(book, scale)
    work = Path(work) if work else book.root / "build"
    out = Path(out) if out else work / "book" / "html"
    if out.exists() and any(out.iterdir()):
        if not (out / ".buildinfo").is_file():
            raise BookError(f"refusing to overwrite {out}: it is not a previous book build; "
                            f"choose an empty or new --out folder")
        shutil.rmtree(out)  # so the site holds exactly the chapters book.yml lists today
    cache_root, key = work / "book-cache", f"{scale}-{package_fingerprint()}"
    for old in cache_root.glob(f"{scale}-*"):  # outputs of older package code are stale
        if old.name != key or not book.cache:
            shutil.rmtree(old)
    cache_dir = (cache_root / key).resolve()
    cache_dir.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    executed = execute_chapters(book, scale, cache_dir) if execute else {}
    src = work / "book-src"
    write_sphinx_project(book, scale if execute else None, src, executed)
    shown = f"at scale {scale!r}" if execute else "without running the notebooks"
    print(f"Rendering the book {shown} into {out}", flush=True)
    run_sphinx(src, out, work / "book-doctrees")
    print(f"built in {(time.monotonic() - start) / 60:.1f} min", flush=True)
    for file, url in find_external_assets(out):
        print(f"warning: {file} loads {url} from the network", file=sys.stderr)
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: ``build`` the book."""
    parser = argparse.ArgumentParser(prog="python -m tools.book",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=("build",))
    parser.add_argument("--config", default=str(DEFAULT_CONFIG), help="book.yml to read")
    parser.add_argument("--scale", choices=SCALES, help="override book.yml and EBJEPA_SCALE")
    parser.add_argument("--out", help="HTML output folder (default build/book/html)")
    parser.add_argument("--no-execute", action="store_true",
                        help="render the notebooks as committed, without outputs")
    args = parser.parse_args(argv)
    try:
        html = build_book(args.config, args.scale, args.out, execute=not args.no_execute)
    except BookError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"The book is in {html}: open {html / 'index.html'} in a browser, or serve it with "
          f"`python -m http.server --directory {html}` and open http://localhost:8000")
    return 0


if __name__ == "__main__":
    sys.exit(main())
