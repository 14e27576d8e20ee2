"""How `make test` spreads its items over pytest-xdist's workers: by file, as ``--dist
loadfile`` does (a notebook's nbval cells share one kernel), except that each notebook's
student-version rerun is a unit of its own, and the longest units are handed out first."""

import pytest

RERUN = "tests/test_notebooks_rerun.py"  # eight notebooks, each run twice: minutes in all


def pytest_collection_modifyitems(items):
    """The reruns first, then the notebooks' cells, then the rest (with ``make test``'s
    ``--no-loadscope-reorder``, the order in which the units go to the workers)."""
    items.sort(key=lambda item: 0 if item.nodeid.startswith(RERUN)
               else 1 if item.nodeid.startswith("notebooks/") else 2)  # stable: cells in order


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``'s scheduler, with each rerun a unit: one worker running all eight
    while the others sat idle was the longest part of CI."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class ByFileRerunsApart(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return nodeid if nodeid.startswith(RERUN) else super()._split_scope(nodeid)

    return ByFileRerunsApart(config, log)
