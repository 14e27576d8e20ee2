"""Each chapter's algorithm is written in its notebook, and the package runs the same code.

A notebook defines its chapter's training loop or step in a cell the learner reads and
edits, and the rest of the notebook trains with that definition. The package holds the
same function for the commands and the shipped checkpoints. These tests fail when the two
differ in code (comments and docstrings may differ: the notebook explains in markdown what
the package says in its docstring), and show that an edit to the cell changes what trains.
Chapter 00's loop trains no shipped run: only its notebook holds it (:func:`chapter_00_loop`).
"""

import ast
import inspect
import textwrap
from pathlib import Path

import pytest
import torch

from ebjepa_tutorial.losses import covariance_term, variance_term, vicreg_loss
from ebjepa_tutorial.training import toy, world
from ebjepa_tutorial.training.image import VICReg
from ebjepa_tutorial.training.loop import History
from research.from_notebook import top_level

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"

# (notebook, function defined in one of its code cells, the package's copy)
PAIRS = [("05_world_model.ipynb", "world_model_step", world.world_model_step)]


def notebook_function(notebook: str, name: str) -> str:
    """The source of ``def name`` in the notebook's code cells (exactly one must define it)."""
    found = [ast.get_source_segment(code, node) for _, code, node in top_level(NOTEBOOKS / notebook)
             if isinstance(node, ast.FunctionDef) and node.name == name]
    assert len(found) == 1, f"{notebook} defines {name} {len(found)} times, not once"
    return found[0]


def chapter_00_loop(source: str | None = None):
    """Notebook 00's ``train_toy``, defined from ``source`` (default: the cell's) with the names
    the cell imports."""
    space = dict(torch=torch, History=History, mlp_encoder=toy.mlp_encoder,
                 two_views=toy.two_views, vicreg_loss=vicreg_loss,
                 course_variance_term=variance_term, course_covariance_term=covariance_term)
    exec(source or notebook_function("00_energy_and_collapse.ipynb", "train_toy"), space)
    return space["train_toy"]


def code_of(source: str) -> str:
    """The function's code as a syntax tree, without its docstring (comments are not in it)."""
    function = ast.parse(textwrap.dedent(source)).body[0]
    body = function.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        function.body = body[1:]
    return ast.dump(function)


def test_code_of_ignores_words_and_sees_code():
    plain = "def f(x):\n    return x + 1\n"
    assert code_of('def f(x):\n    """Add one."""\n    return x + 1  # why\n') == code_of(plain)
    assert code_of("def f(x):\n    return x + 2\n") != code_of(plain)


@pytest.mark.parametrize("notebook, name, package", PAIRS, ids=[p[1] for p in PAIRS])
def test_the_notebook_shows_the_code_the_package_runs(notebook, name, package):
    assert code_of(notebook_function(notebook, name)) == code_of(inspect.getsource(package)), (
        f"{name} in {notebook} and {package.__module__}.{name} differ: change both together")


def test_an_edit_to_chapter_00s_loop_changes_what_trains():
    source = notebook_function("00_energy_and_collapse.ipynb", "train_toy")
    # one more term in the gradient (a scale of the whole gradient would barely move Adam)
    edited = source.replace("loss.backward()", "(loss + z_a.pow(2).mean()).backward()")
    assert edited != source

    x, _ = toy.make_blobs(64, seed=0)
    coeffs = VICReg(inv_coeff=1.0, std_coeff=1.0, cov_coeff=1.0)
    as_shown, _ = chapter_00_loop(source)(x, coeffs, steps=3)
    again, _ = chapter_00_loop(source)(x, coeffs, steps=3)
    changed, _ = chapter_00_loop(edited)(x, coeffs, steps=3)
    with torch.no_grad():
        assert torch.equal(as_shown(x), again(x))  # a run is exactly reproducible
        assert not torch.allclose(changed(x), as_shown(x))
