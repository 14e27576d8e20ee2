"""A notebook's definitions, for the research commands and the tests: one source of truth.

A chapter writes its algorithm in its notebook's code cells. :func:`definitions` runs the
notebook's import statements and the named top-level classes, functions and UPPER_CASE
constants (with the UPPER_CASE constants they read), and nothing else of the cells, so a
research fit runs exactly the code the learner reads.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path
from types import SimpleNamespace

from IPython.core.inputtransformer2 import TransformerManager

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
DEFINITIONS = (ast.FunctionDef, ast.ClassDef)


def _constant(node: ast.stmt) -> str | None:
    """The name an ``UPPER_CASE = ...`` statement assigns, else None."""
    if isinstance(node, ast.Assign) and len(node.targets) == 1:
        target = node.targets[0]
        if isinstance(target, ast.Name) and target.id.isupper():
            return target.id
    return None


def _free_names(node: ast.stmt) -> set[str]:
    """The names ``node`` reads that it neither binds nor takes as arguments (its globals)."""
    names = [n for n in ast.walk(node) if isinstance(n, ast.Name)]
    bound = {n.id for n in names if not isinstance(n.ctx, ast.Load)}
    bound |= {a.arg for n in ast.walk(node) if isinstance(n, ast.arguments)
              for a in (*n.posonlyargs, *n.args, *n.kwonlyargs, n.vararg, n.kwarg) if a}
    return {n.id for n in names if isinstance(n.ctx, ast.Load)} - bound


def top_level(path: Path) -> list[tuple[str, str, ast.stmt]]:
    """``(where, code, statement)`` for the top-level statements of the notebook's code cells,
    in order: ``code`` is the cell's Python (IPython's magics, ``!`` and ``?`` as the calls
    IPython makes of them), which the statement's positions index; ``where`` names the
    notebook and cell."""
    nodes, ipython = [], TransformerManager()
    for index, cell in enumerate(json.loads(path.read_text(encoding="utf-8"))["cells"]):
        if cell["cell_type"] == "code":
            code = ipython.transform_cell("".join(cell["source"]))
            where = f"{path.name}, cell {index}"
            nodes += [(where, code, node) for node in ast.parse(code, filename=where).body]
    return nodes


def definitions(notebook: str | Path, *names: str) -> SimpleNamespace:
    """The notebook's ``names`` (classes, functions, UPPER_CASE constants), each defined once in
    its code cells, run with its imports: ``namespace.NAME``. ``notebook``: a path, or a file
    name in ``notebooks/``."""
    path = Path(notebook) if Path(notebook).exists() else NOTEBOOKS / notebook
    located = [(where, node) for where, _, node in top_level(path)]
    nodes = [node for _, node in located]
    named = {}
    for node in nodes:
        name = node.name if isinstance(node, DEFINITIONS) else _constant(node)
        if name in names:
            if name in named:
                raise ValueError(f"{path.name} defines {name} twice at the top of its cells")
            named[name] = node
    missing = [name for name in names if name not in named]
    if missing:
        raise ValueError(f"{path.name} defines no {', '.join(missing)} at the top of a code cell")
    constants = {_constant(node): node for node in nodes if _constant(node)}
    wanted = dict(named)
    while True:  # the constants the chosen nodes read, and the constants those read
        read = set().union(*(_free_names(node) for node in wanted.values()))
        more = {name: constants[name] for name in read & constants.keys() - wanted.keys()}
        if not more:
            break
        wanted.update(more)
    space = {"__name__": f"notebook_{path.stem}"}
    for where, node in located:  # in the notebook's order, as a "Run All" defines them
        if isinstance(node, ast.Import | ast.ImportFrom) or any(node is n for n in wanted.values()):
            code = compile(ast.Module([node], type_ignores=[]), where, "exec", dont_inherit=True)
            exec(code, space)  # noqa: S102 - the notebook's own definitions
    return SimpleNamespace(**{name: space[name] for name in names})
