"""The course's recorded figures, as the maintainers keep them: written by the benchmarks'
``--record`` (:func:`record`), and rendered into or checked against every page that states
one (README.md, RESULTS.md, TEACHING.md, docs/, the notebooks' markdown), where a figure is
marked ``<!--fig:KEY-->value<!--/fig-->`` (``<!--fig:KEY:spread-->`` for its range).

    python -m tools.figures render   # rewrite every marked figure from reference.json
    python -m tools.figures check    # list every marked figure that disagrees

The notebooks read the same file through ``ebjepa_tutorial.course.reference``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
from pathlib import Path

from ebjepa_tutorial.course.reference import METRICS, REFERENCE_FILE, load
from ebjepa_tutorial.data.paths import atomic_file

ROOT = REFERENCE_FILE.parents[1]  # the repository
# Every recorded figure's format: the notebooks' (reference.METRICS) and those only pages state.
FORMATS = {key: metric.fmt for key, metric in METRICS.items()} | {
    "video_map": "{:.3f}",
    "planning_success_live": "{:.0%}", "planning_success_shipped_fresh": "{:.1%}",
    "planning_cpu_s_shipped": "{:.1f} s", "video_train_min": "{:.1f} min",
    "world_train_min": "{:.1f} min", "vicreg_shipped_probe_acc": "{:.1%}",
    "sigreg_shipped_probe_acc": "{:.1%}", "vicreg_train_min": "{:.1f} min",
    "sigreg_train_min": "{:.1f} min", "vicreg_float32_train_min": "{:.0f} min",
    "sigreg_float32_train_min": "{:.0f} min", "sweep_sigreg_tenfold_points": "{:.0f} points",
    "sweep_vicreg_tenfold_points": "{:.0f} points",
    "image_float32_step_ratio": "{:.1f} times", "world_probe_baseline_px": "{:.1f} px",
} | {f"notebook_{nb:02d}_{scale}": "{:.0f} s" for nb in range(8) for scale in ("ci", "class")}


def record(key: str, value: float, command: str, protocol: str, threads: int,
           path: Path = REFERENCE_FILE, spread: tuple[float, float] | None = None,
           date: str | None = None) -> None:
    """Store a measured ``value`` under ``key`` (atomically; other keys are kept).

    ``spread``: (low, high), over seeds, runs or a 95% interval, which ``protocol``
    names; ``date``: when it was measured (default today). Without one, the key's recorded
    spread is kept.
    """
    if key not in FORMATS:
        raise KeyError(f"unknown reference key {key!r}; known: {sorted(FORMATS)}")
    figures = load(path)
    # a benchmark that measures one run passes no spread, but the pages print the range that a
    # maintainer recorded (<!--fig:KEY:spread-->): dropping it would break every such marker
    kept = figures.get(key, {}).get("spread")
    figures[key] = {"value": float(value), "command": command, "protocol": protocol,
                    "threads": threads, "date": date or datetime.date.today().isoformat()}
    if spread is not None:
        figures[key]["spread"] = [float(spread[0]), float(spread[1])]
    elif kept is not None:
        figures[key]["spread"] = kept
    with atomic_file(path) as f:
        f.write((json.dumps(figures, indent=1, sort_keys=True) + "\n").encode())



FIGURE = re.compile(r"<!--fig:(\w+)(:spread)?-->(.*?)<!--/fig-->", re.S)
PAGES = ("README.md", "RESULTS.md", "TEACHING.md", "docs/*.md", "notebooks/*.ipynb")


def figure_text(key: str, spread: bool = False, figures: dict | None = None) -> str:
    """How the recorded figure ``key`` reads in prose: its value, or its range as low-high."""
    figures = load() if figures is None else figures
    if key not in FORMATS:  # a misspelt marker, or a figure the course has no format for
        raise KeyError(f"unknown figure key {key!r}: fix the marker, or add the key to FORMATS "
                       "in tools/figures.py (or reference.METRICS)")
    if key not in figures:
        raise KeyError(f"no recorded figure {key!r} in {REFERENCE_FILE.name}; record it first "
                       "(its benchmark's --record)")
    fmt, entry = FORMATS[key], figures[key]
    if not spread:
        return fmt.format(entry["value"])
    if "spread" not in entry:
        raise KeyError(f"{key!r} has no recorded spread")
    low, high = (fmt.format(v) for v in entry["spread"])
    unit = re.search(r"[^\d.]*$", low).group()  # "%" or " px": written once, after the range
    return f"{low[:len(low) - len(unit)]}-{high}" if unit and high.endswith(unit) else \
        f"{low}-{high}"


def render(text: str, figures: dict | None = None) -> str:
    """``text`` with every marked figure rewritten from the recorded figures."""
    figures = load() if figures is None else figures
    return FIGURE.sub(lambda m: f"<!--fig:{m[1]}{m[2] or ''}-->"
                                f"{figure_text(m[1], bool(m[2]), figures)}<!--/fig-->", text)


def mismatches(text: str, figures: dict | None = None) -> list[str]:
    """One line per marked figure in ``text`` that disagrees with the recorded one."""
    figures = load() if figures is None else figures
    wrong = []
    for match in FIGURE.finditer(text):
        try:
            expected = figure_text(match[1], bool(match[2]), figures)
        except KeyError as error:
            wrong.append(f"{match[1]}: {error.args[0]}")
            continue
        if match[3] != expected:
            wrong.append(f"{match[1]}{match[2] or ''}: written {match[3]!r}, "
                         f"recorded {expected!r}")
    return wrong


# A figure typed into prose: a number with a unit a run measures (a share, pixels, a time) or
# an AP-like fraction. Markers, maths, code, links and the study-time line are skipped first.
_WORDS = "a|an|one|two|three|four|five|six|seven|eight|nine|ten|eleven|twelve|fifteen|twenty|thirty"
TYPED = re.compile(r"(?<![\w.,-])(\d[\d,]*(?:\.\d+)?\s*(?:%|px\b|CPU-(?:s|minutes|hours)\b|"
                   r"s\b|seconds?\b|min\b|minutes?\b|h\b|hours?\b)|0\.\d{2,3}\b|"
                   rf"\b(?:{_WORDS})[\s-](?:minute|hour)s?\b)", re.I)
_SKIPPED = re.compile(r"<!--fig:.*?<!--/fig-->|<!--.*?-->|\$\$.*?\$\$|\$[^$]*\$|```.*?```|"
                      r"`[^`]*`|\]\([^)]*\)|^\*\*Study time[^\n]*", re.S | re.M)


def typed_figures(text: str) -> list[str]:
    """The figures typed into Markdown ``text`` outside the markers, as written (one space
    before a unit): what :data:`TYPED` finds once markers, maths and code are removed."""
    return [re.sub(r"\s+", " ", m) for m in TYPED.findall(_SKIPPED.sub(" ", text))]


def _pages(root: Path) -> list[Path]:
    return [path for pattern in PAGES for path in sorted(root.glob(pattern))]


def _markdown(path: Path) -> tuple[dict | None, list[dict]]:
    """A page's Markdown as cells ``{"source": [...]}``: a notebook's markdown cells (with the
    notebook, read as plain JSON so a rewrite keeps its layout), or a Markdown file as one."""
    text = path.read_text(encoding="utf-8")
    if path.suffix != ".ipynb":
        return None, [{"source": [text]}]
    notebook = json.loads(text)
    return notebook, [cell for cell in notebook["cells"] if cell["cell_type"] == "markdown"]


def check_pages(root: Path = ROOT, figures: dict | None = None) -> list[str]:
    """Every marked figure in the course's pages that disagrees with the recorded figures."""
    figures = load() if figures is None else figures
    return [f"{path.relative_to(root)}: {line}" for path in _pages(root)
            for cell in _markdown(path)[1]
            for line in mismatches("".join(cell["source"]), figures)]


def render_pages(root: Path = ROOT) -> list[Path]:
    """Rewrite every marked figure in the course's pages; return the files changed."""
    figures, changed = load(), []
    for path in _pages(root):
        notebook, cells = _markdown(path)
        for cell in cells:
            text = "".join(cell["source"])
            if (new := render(text, figures)) != text:
                cell["source"] = new.splitlines(keepends=True)
                changed += [path] if path not in changed else []
        if path in changed:  # whole or not at all: a cut-off write would lose a page
            text = ("".join(cells[0]["source"]) if notebook is None else
                    json.dumps(notebook, indent=1, ensure_ascii=False) + "\n")
            with atomic_file(path) as f:
                f.write(text.encode("utf-8"))
    return changed


def main(argv: list[str] | None = None) -> int:
    """``render`` the pages' figures from reference.json, or ``check`` that they agree."""
    parser = argparse.ArgumentParser(prog="python -m tools.figures",
                                     description=main.__doc__)
    parser.add_argument("command", choices=("render", "check"))
    if parser.parse_args(argv).command == "render":
        try:
            changed = render_pages()
        except KeyError as error:  # a page marks a figure nobody has recorded yet
            print(f"error: {error.args[0]}")
            return 1
        for path in changed:
            print(f"rewrote the figures of {path}")
        return 0
    wrong = check_pages()
    print("\n".join(wrong) or "every marked figure agrees with checkpoints/reference.json")
    return 1 if wrong else 0


if __name__ == "__main__":
    raise SystemExit(main())
