"""Every chapter's main path stands on its own: its optional part is marked where it is.

A chapter may end in (or hold) an optional part: headings that start ``Optional:`` and,
under them, cells tagged ``optional`` in ``metadata.tags``. A learner who skips every
tagged cell must still be able to run the chapter, so no main-path code cell may read a
name that only optional cells have assigned. The check reads the cells with ``ast`` and
runs nothing, so it takes well under a second.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.ipynb"))
TAG, MARK = "optional", "Optional:"
CHAPTERS_WITH_OPTIONAL_PART = ("03", "06", "07")  # the hard chapters (issue 54)
HEADING = re.compile(r"^(#{1,6})\s+(.*\S)\s*$")
SCOPES = (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda,
          ast.ListComp, ast.SetComp, ast.DictComp, ast.GeneratorExp)


def is_tagged(cell: dict) -> bool:
    return TAG in cell.get("metadata", {}).get("tags", [])


def source(cell: dict) -> str:
    text = cell["source"]
    return text if isinstance(text, str) else "".join(text)


def placements(cells: list[dict]) -> list[bool | None]:
    """Per cell: True if its headings place it in an optional part, False if in the main
    path, None for a markdown cell that begins in one and ends in the other.

    A cell is optional while any enclosing heading (the latest of each level above it)
    starts with ``Optional:``; a heading of the same or a higher level ends that part.
    """
    enclosing: dict[int, bool] = {}  # heading level -> does that heading start "Optional:"?
    placed = []
    for cell in cells:
        if cell["cell_type"] != "markdown":
            placed.append(any(enclosing.values()))
            continue
        seen, fenced = set(), False
        for line in source(cell).splitlines():
            fenced ^= line.lstrip().startswith("```")  # a '#' in a code block is no heading
            match = None if fenced else HEADING.match(line)
            if match:
                level = len(match[1])
                enclosing = {k: v for k, v in enclosing.items() if k < level}
                enclosing[level] = match[2].startswith(MARK)
            if line.strip():
                seen.add(any(enclosing.values()))
        placed.append(seen.pop() if len(seen) == 1 else
                      any(enclosing.values()) if not seen else None)
    return placed


def marking_problems(cells: list[dict]) -> list[str]:
    """Where the ``optional`` tags and the ``Optional:`` headings disagree, in words."""
    problems = []
    for i, (cell, placed) in enumerate(zip(cells, placements(cells))):
        kind = cell["cell_type"]
        if placed is None:
            problems.append(f"markdown cell {i} starts in one part and ends in the other: "
                            "split it at the heading")
        elif is_tagged(cell) and not placed:
            problems.append(f"{kind} cell {i} is tagged {TAG!r} but no heading above it "
                            f"starts with {MARK!r}")
        elif placed and not is_tagged(cell):
            problems.append(f"{kind} cell {i} lies under a heading that starts with {MARK!r} "
                            f"but is not tagged {TAG!r}")
    return problems


def bound_inside(scope: ast.AST) -> set[str]:
    """The names a function, class, lambda or comprehension binds for its own body."""
    names = set()
    arguments = getattr(scope, "args", None)
    if isinstance(arguments, ast.arguments):
        every = arguments.posonlyargs + arguments.args + arguments.kwonlyargs
        every += [a for a in (arguments.vararg, arguments.kwarg) if a is not None]
        names |= {a.arg for a in every}
    for node in ast.walk(scope):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, SCOPES[:3]) and node is not scope:
            names.add(node.name)
    return names


def assigned_and_loaded(code: str) -> tuple[set[str], set[str]]:
    """The global names a cell assigns, and those it reads from outside itself.

    Names bound inside a function, class, lambda or comprehension (its arguments and
    its own assignments) are that scope's, neither assigned nor read globally.
    """
    # IPython magics and shell escapes are no Python: blank them, keeping the line numbers
    lines = ["" if line.lstrip().startswith(("%", "!")) else line for line in code.splitlines()]
    tree = ast.parse("\n".join(lines))
    assigned, loaded = set(), set()

    def visit(node: ast.AST, bound: set[str] | None) -> None:  # bound is None at the top
        if isinstance(node, (ast.Import, ast.ImportFrom)) and bound is None:
            assigned.update(a.asname or a.name.split(".")[0] for a in node.names)
        if isinstance(node, SCOPES[:3]) and bound is None:
            assigned.add(node.name)
        if isinstance(node, ast.Name):
            if isinstance(node.ctx, ast.Store) and bound is None:
                assigned.add(node.id)
            elif isinstance(node.ctx, ast.Load) and node.id not in (bound or ()):
                loaded.add(node.id)
        inner = (bound or set()) | bound_inside(node) if isinstance(node, SCOPES) else bound
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(tree, None)
    return assigned, loaded


def dependency_problems(cells: list[dict]) -> list[str]:
    """Main-path code cells that read a name which, at that point, only optional cells
    have assigned (so they fail, or read something else, when the optional part is
    skipped). Names that main-path cells assign too count as main-path."""
    main, optional, problems = set(), set(), []
    for i, cell in enumerate(cells):
        if cell["cell_type"] != "code":
            continue
        assigned, loaded = assigned_and_loaded(source(cell))
        if is_tagged(cell):
            optional |= assigned
            continue
        missing = sorted((loaded - assigned) & (optional - main))
        if missing:
            problems.append(f"main-path code cell {i} reads {', '.join(missing)}, which only "
                            f"cells tagged {TAG!r} assign: assign it on the main path, or "
                            "make this cell optional")
        main |= assigned
    return problems


def has_optional_part(cells: list[dict]) -> bool:
    return any(is_tagged(c) for c in cells) and any(placements(cells))


def cells_of(path: Path) -> list[dict]:
    return json.loads(path.read_text(encoding="utf-8"))["cells"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_optional_part_is_marked_where_it_is_tagged(path):
    problems = marking_problems(cells_of(path))
    assert not problems, f"{path.name}:\n" + "\n".join(problems)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_main_path_runs_without_the_optional_part(path):
    problems = dependency_problems(cells_of(path))
    assert not problems, f"{path.name}:\n" + "\n".join(problems)


@pytest.mark.parametrize("chapter", CHAPTERS_WITH_OPTIONAL_PART)
def test_hard_chapters_have_an_optional_part(chapter):
    found = [p for p in NOTEBOOKS if p.name.startswith(f"{chapter}_")]
    assert len(found) == 1, f"no single notebook {chapter}_*.ipynb: {found}"
    assert has_optional_part(cells_of(found[0])), (
        f"{found[0].name} has no optional part: headings starting {MARK!r} over cells "
        f"tagged {TAG!r}")


# --- the checks themselves, on small notebooks built in memory ---------------------------

def md(text: str) -> dict:
    return {"cell_type": "markdown", "metadata": {}, "source": text}


def code(text: str, optional: bool = False) -> dict:
    return {"cell_type": "code", "metadata": {"tags": [TAG] if optional else []},
            "source": text, "outputs": [], "execution_count": None}


def opt_md(text: str) -> dict:
    return {**md(text), "metadata": {"tags": [TAG]}}


def sound_notebook() -> list[dict]:
    return [md("# 99 · A chapter\n\n## 1. Main"), code("import math\nx = 1\nrows = [x]"),
            opt_md("## Optional: 2. Depth\n\nThe main path is complete without it."),
            code("y = x + 1\nrows = [x, y]", optional=True),
            opt_md("### A subsection of the optional part"),
            code("def twice(y):\n    return 2 * y\nz = [y for y in range(3)]", optional=True),
            md("## Summary\n\nDone."), code("print(x, rows, math.pi)")]


def test_a_sound_notebook_passes():
    cells = sound_notebook()
    assert marking_problems(cells) == [] and dependency_problems(cells) == []
    assert has_optional_part(cells)


def test_a_main_cell_that_reads_an_optional_variable_is_caught():
    cells = sound_notebook() + [code("print(y)")]  # y: assigned only in the optional part
    problems = dependency_problems(cells)
    assert len(problems) == 1 and "cell 8 reads y" in problems[0]
    # read inside a main-path function, it fails as surely when the function is called
    cells = sound_notebook() + [code("def show():\n    return twice(x)\nshow()")]
    assert "reads twice" in " ".join(dependency_problems(cells))


def test_a_name_bound_locally_or_on_the_main_path_is_no_dependency():
    cells = sound_notebook() + [
        code("def f(y):\n    return y\nsquares = [y * y for y in range(3)]\n"
             "f(lambda twice: twice)"),
        code("y = 5"), code("print(y)")]  # y assigned on the main path before it is read
    assert dependency_problems(cells) == []


def test_a_tag_without_its_heading_and_a_heading_without_its_tags_are_caught():
    cells = sound_notebook()
    cells[1] = code("import math\nx = 1\nrows = [x]", optional=True)  # main section, tagged
    cells[3] = code("y = x + 1\nrows = [x, y]")  # optional section, untagged
    problems = marking_problems(cells)
    assert len(problems) == 2
    assert "cell 1 is tagged 'optional' but no heading" in problems[0]
    assert "cell 3 lies under a heading that starts with 'Optional:'" in problems[1]
    # one markdown cell that runs from the main path into the optional part
    cells = sound_notebook()
    cells[2] = md("Main-path prose.\n\n## Optional: 2. Depth")
    assert "split it at the heading" in marking_problems(cells)[0]


def test_a_heading_inside_a_code_block_opens_no_part():
    cells = [md("## 1. Main\n\n```\n## Optional: not a heading\n```\nStill main."),
             code("x = 1")]
    assert marking_problems(cells) == [] and not has_optional_part(cells)
