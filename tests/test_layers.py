"""The package's layers follow the data: each imports only itself and layers below it.

Read bottom to top: utilities, data, worlds, augmentations, networks, losses,
the multi-process wrappers of the losses, training, evaluation, planning,
pictures, then the teaching layer (course). No import cycle, and nothing below
the course imports it. The research commands (``research/``) and the build
tooling (``tools/``) sit beside the package: they import it, it never imports
them, and only the package is installed.
"""

import ast
import fnmatch
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ebjepa_tutorial"
LAYERS = ["utils", "data", "envs", "augment", "models", "losses", "distributed", "training",
          "evaluation", "planning", "viz", "course"]
BESIDE = ("research", "tools")  # import the package; never imported by it


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


def imported_names(path: Path) -> set[str]:
    """Every absolute module name a file imports: ``import x``, ``from x import y``, and the
    string given to ``importlib.import_module`` or ``__import__`` (relative imports stay
    inside the package, so they cannot reach a folder beside it)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names.add(node.module)
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            called = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(
                node.func, "id", None)
            if called in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                names.add(node.args[0].value)
    return names


def test_imported_names_sees_every_way_of_importing(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("import research.sweep\nfrom tools import book\nfrom . import x\n"
                      "def f():\n    importlib.import_module('research.launch')\n")
    assert imported_names(source) == {"research.sweep", "tools", "research.launch"}


def test_the_package_never_imports_research_or_tools():
    reached = sorted((name, m) for name, path in modules().items()
                     for m in imported_names(path) if m.split(".")[0] in BESIDE)
    assert reached == [], "the package imports code beside it: " + ", ".join(
        f"{name} -> {m}" for name, m in reached)


def test_only_the_package_is_installed():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    setuptools = pytest.importorskip("setuptools")
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    find = config["tool"]["setuptools"]["packages"]["find"]
    finder = (setuptools.find_namespace_packages if find.get("namespaces", True)
              else setuptools.find_packages)
    installed = finder(where=str(ROOT / find.get("where", ["."])[0]),
                       include=find.get("include", ["*"]), exclude=find.get("exclude", []))
    assert "ebjepa_tutorial" in installed
    assert [p for p in installed if p.split(".")[0] != "ebjepa_tutorial"] == []
    for beside in BESIDE:  # the folders exist and the patterns would not pick them up
        assert (ROOT / beside / "__init__.py").is_file()
        assert not any(fnmatch.fnmatch(beside, pattern) for pattern in find["include"])


@pytest.mark.slow  # a fresh interpreter imports torch
def test_lower_layers_load_without_the_course():
    top = LAYERS.index("course")
    lower = sorted(m for m in modules() if layer(m) is not None and layer(m) < top)
    code = (f"import importlib, sys\nfor m in {lower!r}: importlib.import_module(m)\n"
            "print([m for m in sys.modules if m.startswith('ebjepa_tutorial.course')])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.slow  # a fresh interpreter imports torch
def test_the_whole_package_loads_without_research_or_tools():
    code = ("import importlib, sys\n"
            f"for m in {sorted(modules())!r}: importlib.import_module(m)\n"
            f"print(sorted({{m.split('.')[0] for m in sys.modules}} & {set(BESIDE)!r}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT)
    assert out.stdout.strip() == "[]"
