"""research.from_notebook: a notebook's named definitions, run with its imports and nothing else."""

import json

import pytest
import torch

from research.from_notebook import definitions


def notebook(path, *cells):
    """A notebook at ``path`` with a markdown cell, then one code cell per source."""
    body = [{"cell_type": "markdown", "metadata": {}, "source": ["# def not_code():"]}]
    body += [{"cell_type": "code", "metadata": {}, "execution_count": None, "outputs": [],
              "source": source} for source in cells]
    path.write_text(json.dumps({"cells": body, "metadata": {}, "nbformat": 4,
                                "nbformat_minor": 5}))
    return path


def test_the_named_definitions_run_with_the_imports_and_the_constants_they_read(tmp_path):
    path = notebook(tmp_path / "nb.ipynb",
                    "%matplotlib inline\nimport math\nBASE = 3.0\nSCALE = 2 * BASE\n"
                    "UNUSED = undefined_name\nraise RuntimeError('a cell statement ran')",
                    "from dataclasses import dataclass\n\n\n@dataclass\nclass Box:\n"
                    "    side: float = SCALE\n",
                    "def area(box):\n    return math.pi * 0 + box.side ** 2\n\n\n"
                    "print('a cell statement ran')")
    found = definitions(path, "area", "Box")
    assert found.area(found.Box()) == 36.0  # SCALE = 2 * BASE, both found; UNUSED never runs
    assert found.Box.__module__ == "notebook_nb" and not hasattr(found, "SCALE")
    assert found.area.__code__.co_filename == "nb.ipynb, cell 3"  # where a traceback points
    assert definitions(path, "BASE").BASE == 3.0


def test_ipython_syntax_and_a_functions_own_names_do_not_get_in_the_way(tmp_path):
    path = notebook(tmp_path / "nb.ipynb",
                    "%%capture\nprint('hidden')", "files = !ls\nlen?",
                    "K = config.rollout_steps  # a cell's constant, from the cell above",
                    "text = ('%d of %d'\n        % (1, 2))",
                    "def horizons(K):  # an argument, not the cell's K\n"
                    "    H = K + 1  # a local, not a constant\n    return list(range(1, H))\n")
    assert definitions(path, "horizons").horizons(3) == [1, 2, 3]


def test_a_name_defined_nowhere_or_twice_is_refused(tmp_path):
    path = notebook(tmp_path / "nb.ipynb", "def f():\n    pass\n", "def f():\n    return 1\n")
    with pytest.raises(ValueError, match="defines f twice"):
        definitions(path, "f")
    with pytest.raises(ValueError, match="defines no g, not_code"):
        definitions(path, "g", "not_code")


def test_notebook_07_gives_its_cost_head_and_planner():
    found = definitions("07_beyond_the_paper.ipynb", "CostToGo", "TwoLevel", "load_fit")
    z = torch.zeros(2, 4)
    assert found.CostToGo(4)(z, z).tolist() == [0.0, 0.0]  # a distance: 0 from z to itself
    assert found.TwoLevel.__dataclass_params__.frozen
