"""Write student versions of the notebooks: solutions out, everything else identical.

A notebook is written once, with its solutions. In a code cell, a solution is
the lines between ``### BEGIN SOLUTION`` and ``### END SOLUTION``, inside the
function that is the exercise. The student version replaces each region by a
comment and a ``raise NotImplementedError`` at the same indentation: they ask
the learner to write the function and say how to get a hint. The hints
themselves (the idea, the formula, an outline of the code) live beside the
checkers, in ``ebjepa_tutorial/course/exercises/hints.yaml``, one place per exercise, and
come from ``exercises.hint("name")`` or a failed check, so no code of the
solution stays in the student version; a ``# HINT:`` line inside a region is an
error. The student version also drops the text of markdown cells between
``<!-- BEGIN SOLUTION -->`` and ``<!-- END SOLUTION -->`` (sentences about the
solutions), and all outputs. Each exercise's checker hands the course's
implementation to the rest of the notebook while the stub is unsolved, so a
student version runs to the end::

    python -m tools.student notebooks student   # what `make student` runs

A student notebook that already exists is kept (it holds the learner's work);
``--overwrite`` replaces it.
"""

from __future__ import annotations

import argparse
import copy
import re
from pathlib import Path

from ebjepa_tutorial.data.paths import atomic_file

BEGIN = re.compile(r"^(\s*)### BEGIN SOLUTION\s*$")
END = re.compile(r"^\s*### END SOLUTION\s*$")
HINT = re.compile(r"^\s*# HINT:")
DEF = re.compile(r"^(\s*)def (\w+)\(")
MARKDOWN_SOLUTION = re.compile(r"[ \t]*<!-- BEGIN SOLUTION -->.*?<!-- END SOLUTION -->", re.S)


def _exercise_name(lines: list[str], indent: str) -> str | None:
    """The function the region at ``indent`` belongs to: the nearest ``def`` above it that
    is indented less."""
    for line in reversed(lines):
        if (match := DEF.match(line)) and len(match.group(1)) < len(indent):
            return match.group(2)
    return None


def stub(name: str | None, indent: str = "") -> list[str]:
    """The lines that stand for a solution region of the exercise ``name``."""
    if name is None:
        return [f"{indent}raise NotImplementedError('Exercise: the text above says what to "
                "write here.')"]
    ask = f'exercises.hint("{name}")'
    message = f"Exercise: write {name}; {ask} gives a hint."
    return [f"{indent}# Your code here. Stuck? {ask} gives a hint, one level at a time.",
            f"{indent}raise NotImplementedError({message!r})"]


def strip_solutions(source: str) -> str:
    """Replace every solution region in a code cell's ``source`` by a stub."""
    out, indent = [], None
    for number, line in enumerate(source.splitlines(), start=1):
        if indent is None and (begin := BEGIN.match(line)):
            indent = begin.group(1)
            out.extend(stub(_exercise_name(out, indent), indent))
        elif indent is not None and END.match(line):
            indent = None
        elif indent is not None:
            if HINT.match(line):
                raise ValueError(f"line {number}: a '# HINT:' line in a solution; hints live "
                                 "beside the checkers, in ebjepa_tutorial/course/exercises")
        elif END.match(line):
            raise ValueError(f"line {number}: END SOLUTION without BEGIN SOLUTION")
        else:
            out.append(line)
    if indent is not None:
        raise ValueError("BEGIN SOLUTION without END SOLUTION")
    return "\n".join(out) + ("\n" if source.endswith("\n") else "")


def student_notebook(notebook):
    """A copy of ``notebook`` (a notebook's dict, as ``nbformat.read`` gives it) with solutions
    (code and markdown) stripped and outputs removed."""
    student = copy.deepcopy(notebook)  # a dict walk: importing nbformat costs seconds
    for cell in student["cells"]:
        kind = cell["cell_type"]
        if kind == "code":
            cell["source"] = strip_solutions(cell["source"])
            cell["outputs"], cell["execution_count"] = [], None
        elif kind == "markdown":
            cell["source"] = MARKDOWN_SOLUTION.sub("", cell["source"])
        if re.search(r"(?i)(begin|end)\s+solution", cell["source"]):  # a marker matched nothing
            raise ValueError(f"a solution marker is left in a {kind} cell, so its "
                             f"solution would stay: {cell['source'][:80]!r}")
    return student


def write_student_versions(src: str | Path, dst: str | Path, overwrite: bool = False) -> list[Path]:
    """Write the student version of every ``src/*.ipynb`` into ``dst``; return the paths written.

    A student notebook already in ``dst`` holds a learner's work: it is kept
    unless ``overwrite`` (delete it to start that chapter afresh).
    """
    import nbformat

    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    written = []
    for path in sorted(src.glob("*.ipynb")):
        if (dst / path.name).exists() and not overwrite:
            print(f"kept {dst / path.name}: it may hold your work (delete it to start afresh)")
            continue
        try:
            notebook = student_notebook(nbformat.read(path, as_version=4))
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
        nbformat.validate(notebook)
        with atomic_file(dst / path.name) as f:  # whole or absent: a cut-off write is never kept
            f.write((nbformat.writes(notebook).rstrip("\n") + "\n").encode("utf-8"))
        written.append(dst / path.name)
    return written


def main(argv: list[str] | None = None) -> None:
    """Command line: ``python -m tools.student [SOURCE] [TARGET] [--overwrite]``."""
    parser = argparse.ArgumentParser(prog="python -m tools.student", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", nargs="?", default="notebooks", help="the notebooks' folder")
    parser.add_argument("target", nargs="?", default="student", help="where to write them")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace student notebooks that exist (they may hold your work)")
    args = parser.parse_args(argv)
    for written in write_student_versions(args.source, args.target, args.overwrite):
        print(f"wrote {written}")


if __name__ == "__main__":
    main()
