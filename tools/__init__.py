"""Build tooling for maintainers, run from the repository root: ``python -m tools.book build``
renders the online book from ``book.yml``, and ``python -m tools.student`` writes the student
versions of the notebooks (``make book``, ``make student``). These modules import
``ebjepa_tutorial``; the package never imports them, and they are not installed with it.
"""
