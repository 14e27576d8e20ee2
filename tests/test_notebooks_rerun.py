"""The student versions run to the end with nothing solved, and survive re-running any cell.

nbval runs every notebook once, with its solutions, top to bottom (the book's test
renders them without running them again).
This runs each notebook's student version (``make student``: every exercise
left as its stub) top to bottom, as a learner's "Run All" does, then every cell
again, the edit-and-rerun habit of a class. The exercise cells are the only
difference between the two versions, so the pair covers both.
"""

import os
import re
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_the_student_version_runs_to_the_end_and_every_cell_twice(path, monkeypatch):
    import nbformat  # slow imports, kept out of the collection of the fast tests
    from nbclient import NotebookClient

    from tools.student import student_notebook

    monkeypatch.setenv("EBJEPA_SCALE", "ci")
    monkeypatch.setenv("MPLBACKEND", "agg")
    notebook = student_notebook(nbformat.read(path, as_version=4))
    client = NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}})
    with client.setup_kernel(env=dict(os.environ)):
        for _ in range(2):
            for index, cell in enumerate(notebook.cells):
                client.execute_cell(cell, index)  # raises CellExecutionError on failure
    printed = "".join(output.get("text", "") for cell in notebook.cells
                      if cell.cell_type == "code" for output in cell.outputs)
    stubbed = {name for cell in notebook.cells if "raise NotImplementedError" in cell.source
               for name in re.findall(r"^def (\w+)\(", cell.source, flags=re.M)}
    handed_over = "is not implemented yet, so any cell below that uses it gets the course's"
    for name in stubbed:  # every exercise said it handed over the course's implementation
        assert f"{name} {handed_over}" in printed, f"{name} did not hand over"
