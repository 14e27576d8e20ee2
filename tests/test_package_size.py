"""The helper package keeps the shape DESIGN.md asks of it ("The package"): no function
longer than about a screen (40 lines), no dataclass (the configs a learner meets) with more
than 10 fields. (Its total size, at most 4,500 lines, is issue 53's open target.)"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "ebjepa_tutorial"
MAX_FUNCTION, MAX_FIELDS = 40, 10


def trees():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path.relative_to(PACKAGE.parent), ast.parse(path.read_text())


def is_dataclass(node: ast.ClassDef) -> bool:
    names = {getattr(d, "id", None) or getattr(getattr(d, "func", None), "id", None)
             for d in node.decorator_list}
    return "dataclass" in names


def fields(node: ast.ClassDef) -> int:
    return sum(isinstance(item, ast.AnnAssign) for item in node.body)


def test_no_function_is_longer_than_40_lines():
    long = [f"{path}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
            for path, tree in trees() for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            and node.end_lineno - node.lineno + 1 > MAX_FUNCTION]
    assert not long, "functions over 40 lines: " + "; ".join(long)


def test_no_config_has_more_than_10_fields():
    big = [f"{path} {node.name} ({fields(node)} fields)" for path, tree in trees()
           for node in ast.walk(tree)
           if isinstance(node, ast.ClassDef) and is_dataclass(node) and fields(node) > MAX_FIELDS]
    assert not big, "dataclasses over 10 fields: " + "; ".join(big)


def test_the_counts_see_what_they_count():
    tree = ast.parse("from dataclasses import dataclass\n\n@dataclass(frozen=True)\nclass C:\n"
                     "    a: int = 1\n    b: int = 2\n\n    def f(self):\n        return 1\n")
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef))
    method = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef))
    assert is_dataclass(cls) and fields(cls) == 2
    assert method.end_lineno - method.lineno + 1 == 2
