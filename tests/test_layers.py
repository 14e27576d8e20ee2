"""The package's layers follow the data: each imports only itself and layers below it.

Read bottom to top: utilities, the helpers of multi-process training, data,
worlds, augmentations, networks, losses, training, evaluation, planning,
pictures, then the teaching layer (course) and the command lines. No import
cycle, and nothing below the course imports it.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "ebjepa_tutorial"
LAYERS = ["utils", "distributed", "data", "envs", "augment", "models", "losses", "training",
          "evaluation", "planning", "viz", "course", "commands"]


def modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package is its ``__init__``)."""
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The package modules that ``name`` imports anywhere in its body, functions included."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets.add(base)  # `from pkg import x` runs pkg's __init__ first
            for alias in node.names:  # ... and imports x itself when x is a submodule
                full = f"{base}.{alias.name}"
                targets.add(full if full in known else base)
    return {t for t in targets if t in known and t != name}


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(name, path, set(known)) for name, path in known.items()}


def layer(name: str) -> int | None:
    parts = name.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else None


def test_every_module_has_a_layer():
    assert [m for m in modules() if m != "ebjepa_tutorial" and layer(m) is None] == []


def test_each_module_imports_only_its_layer_and_those_below():
    upward = [(m, t) for m, targets in graph().items() for t in targets
              if layer(m) is not None and layer(t) is not None and layer(t) > layer(m)]
    assert upward == [], "imports up a layer: " + ", ".join(f"{m} -> {t}" for m, t in upward)


def test_no_import_cycle():
    edges, state, cycles = graph(), {}, []

    def visit(node, trail):
        state[node] = "open"
        for nxt in sorted(edges[node]):
            if state.get(nxt) == "open":
                cycles.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    assert cycles == [], "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


@pytest.mark.slow  # a fresh interpreter imports torch
def test_lower_layers_load_without_the_course_or_the_commands():
    top = LAYERS.index("course")
    lower = sorted(m for m in modules() if layer(m) is not None and layer(m) < top)
    code = (f"import importlib, sys\nfor m in {lower!r}: importlib.import_module(m)\n"
            "print([m for m in sys.modules if m.startswith(('ebjepa_tutorial.course', "
            "'ebjepa_tutorial.commands'))])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
