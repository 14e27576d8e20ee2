"""Every notebook survives re-running any cell: run it top to bottom, then every cell again.

nbval (``make test``) checks the top-to-bottom run; this adds the edit-and-rerun
habit of a class, where a learner runs a cell a second time after changing it.
"""

import os
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_every_cell_can_run_twice(path, monkeypatch):
    import nbformat  # slow imports, kept out of the collection of the fast tests
    from nbclient import NotebookClient

    monkeypatch.setenv("EBJEPA_SCALE", "ci")
    monkeypatch.setenv("MPLBACKEND", "agg")
    notebook = nbformat.read(path, as_version=4)
    client = NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}})
    with client.setup_kernel(env=dict(os.environ)):
        for _ in range(2):
            for index, cell in enumerate(notebook.cells):
                client.execute_cell(cell, index)  # raises CellExecutionError on failure
