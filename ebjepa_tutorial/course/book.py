"""Build the course's online book from ``book.yml``, fully offline.

    python -m ebjepa_tutorial.course.book build [--scale ci|class|full] [--out DIR] [--config FILE]

``book.yml`` names the title, authors, chapters (notebooks, in order) and how
to execute them. ``build`` writes a Sphinx project into ``build/book-src``
(generated ``conf.py`` and title page, a link to the chapters' folder, a local
MathJax), then runs sphinx-build: myst-nb executes every chapter at the chosen
scale and the HTML site lands in ``build/book/html``. Executed notebooks are
cached (jupyter-cache, ``build/book-cache``) per scale and per version of the
package's code, so a second build is fast. Nothing comes from the network.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

from .presets import SCALES

PACKAGE_DIR = Path(__file__).resolve().parents[1]  # ebjepa_tutorial/
DEFAULT_CONFIG = PACKAGE_DIR.parent / "book.yml"
MATHJAX_DIR = "mathjax"  # under _static/
BOOK_KEYS = {"title", "subtitle", "authors", "description", "chapters", "execute"}
EXECUTE_KEYS = {"scale", "cache", "timeout"}


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
                timeout=int(execute.get("timeout", 1800)))
    check_book(book, path.name)
    return book


def check_book(book: Book, name: str = "book.yml") -> None:
    """Raise BookError if a chapter is missing or outside the book, or a setting is invalid."""
    if book.scale not in SCALES:
        raise BookError(f"{name}: execute.scale {book.scale!r} is not one of {SCALES}")
    if book.timeout <= 0:
        raise BookError(f"{name}: execute.timeout must be a positive number of seconds")
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
    """A short hash of the package's Python sources (but this file), which notebooks run."""
    digest = hashlib.sha256()
    for file in sorted(PACKAGE_DIR.rglob("*.py")):
        if file.name == "book.py":  # building the book does not change what notebooks print
            continue
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


def conf_py(book: Book, cache_dir: Path | None) -> str:
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
        "nb_execution_mode": "cache" if book.cache else "force",
        "nb_execution_cache_path": str(cache_dir) if cache_dir else "",
        "nb_execution_timeout": book.timeout,
        "nb_execution_raise_on_error": True,
        "nb_execution_show_tb": True,
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
    lines = ["# Generated by `python -m ebjepa_tutorial.course.book build` from book.yml; "
             "edits are lost."]
    lines += [f"{key} = {value!r}" for key, value in settings.items()]
    return "\n".join(lines) + "\n"


def index_md(book: Book, scale: str) -> str:
    """The title page: title, authors, description, the scale it was run at, the chapters."""
    docs = [str(Path(chapter).with_suffix("").as_posix()) for chapter in book.chapters]
    parts = [f"# {book.title}", ""]
    if book.subtitle:
        parts += [f"*{book.subtitle}*", ""]
    if book.authors:
        parts += ["By " + ", ".join(book.authors), ""]
    if book.description:
        parts += [book.description.strip(), ""]
    parts += [f"The notebooks on these pages were executed at scale `{scale}` "
              f"(`EBJEPA_SCALE={scale}`).", ""]
    parts += ["```{toctree}", ":caption: Chapters", ":maxdepth: 1", "", *docs, "```", ""]
    return "\n".join(parts)


def link_or_copy(source: Path, target: Path) -> None:
    """Make ``target`` show ``source``: a folder of notebooks is symlinked (they then run in
    their own folder); pages are copied, because Sphinx resolves a link between pages
    from where a symlink points, not from where the book shows it."""
    copy = shutil.copytree if source.is_dir() else shutil.copy2
    if not (source.is_dir() and any(source.glob("*.ipynb"))):
        copy(source, target)
        return
    try:
        target.symlink_to(source, target_is_directory=True)
    except OSError:  # no symlinks (e.g. Windows without developer mode)
        copy(source, target)


def write_sphinx_project(book: Book, scale: str, src: Path, cache_dir: Path | None) -> None:
    """Fill ``src`` with conf.py, index.md, links to the chapters and MathJax in _static."""
    src.mkdir(parents=True, exist_ok=True)
    for entry in src.iterdir():  # start clean, but keep the (large, unchanging) _static copy
        if entry.name == "_static":
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()
    (src / "conf.py").write_text(conf_py(book, cache_dir), encoding="utf-8")
    (src / "index.md").write_text(index_md(book, scale), encoding="utf-8")
    for top in sorted({Path(chapter).parts[0] for chapter in book.chapters}):
        link_or_copy(book.root / top, src / top)
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


def run_sphinx(src: Path, out: Path, doctrees: Path, scale: str) -> None:
    """Run sphinx-build (which executes the notebooks) with ``EBJEPA_SCALE=scale``."""
    command = [sys.executable, "-m", "sphinx", "-b", "html", "-E", "-d", str(doctrees),
               str(src), str(out)]
    env = dict(os.environ, EBJEPA_SCALE=scale, PYDEVD_DISABLE_FILE_VALIDATION="1")
    log: list[str] = []
    failing = False  # after a notebook fails, Sphinx's crash report would only confuse
    with subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, bufsize=1) as process:
        for line in process.stdout:
            log.append(line)
            if not failing and not is_noise(line):
                print(line, end="", flush=True)
            failing = failing or "[mystnb.exec]" in line
    if process.returncode != 0:
        raise BookError(explain_failure("".join(log), scale, process.returncode))


def explain_failure(log: str, scale: str, returncode: int) -> str:
    """One message for a failed sphinx-build: which notebook, which cell, which error."""
    failed = re.findall(r"ExecutionError: (\S+)", log)
    if not failed:
        return f"sphinx-build failed with exit code {returncode} (messages above)"
    plain = re.sub(r"\x1b\[[0-9;]*m", "", log)  # drop terminal colours
    plain = plain.split("[mystnb.exec]")[0]  # the notebook's traceback, not Sphinx's
    cell = re.search(r"(?:executing the following cell|preview of the cell contents):\n-+\n"
                     r"(.*?)\n-+\n", plain, re.S)
    errors = re.findall(r"^((?:\w+\.)*\w+(?:Error|Exception|Interrupt)\b.*)$", plain, re.M)
    message = f"notebook {Path(failed[-1]).name} failed while executing at scale {scale}"
    if cell:
        message += " in the cell\n\n    " + cell.group(1).replace("\n", "\n    ") + "\n"
    if errors:
        message += f"\nwith {errors[-1]}\n"
    if "CellTimeoutError" in plain:
        message += "\nIf the cell is only slow, raise execute.timeout in book.yml.\n"
    return message + (f"\nReproduce it with `EBJEPA_SCALE={scale} make lab`, fix the notebook "
                      f"or the package, then build again.")


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
               out: str | Path | None = None, work: str | Path | None = None) -> Path:
    """Build the HTML book; return the folder with ``index.html``.

    ``work`` holds the generated Sphinx project and the execution cache
    (default: ``build/`` next to book.yml); ``out`` defaults to ``work/book/html``.
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
    cache_dir = None
    if book.cache:
        cache_root, key = work / "book-cache", f"{scale}-{package_fingerprint()}"
        for old in cache_root.glob(f"{scale}-*"):  # outputs of older package code are stale
            if old.name != key:
                shutil.rmtree(old)
        cache_dir = (cache_root / key).resolve()
    src = work / "book-src"
    write_sphinx_project(book, scale, src, cache_dir)
    print(f"Building the book at scale {scale!r} into {out}", flush=True)
    run_sphinx(src, out, work / "book-doctrees", scale)
    for file, url in find_external_assets(out):
        print(f"warning: {file} loads {url} from the network", file=sys.stderr)
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: ``build`` the book."""
    parser = argparse.ArgumentParser(prog="python -m ebjepa_tutorial.course.book",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=("build",))
    parser.add_argument("--config", default=str(DEFAULT_CONFIG), help="book.yml to read")
    parser.add_argument("--scale", choices=SCALES, help="override book.yml and EBJEPA_SCALE")
    parser.add_argument("--out", help="HTML output folder (default build/book/html)")
    args = parser.parse_args(argv)
    try:
        html = build_book(args.config, args.scale, args.out)
    except BookError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"The book is in {html}: open {html / 'index.html'} in a browser, or serve it with "
          f"`python -m http.server --directory {html}` and open http://localhost:8000")
    return 0


if __name__ == "__main__":
    sys.exit(main())
