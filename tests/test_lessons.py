"""The notebooks' shape as lessons: how long they are, and what each one opens with."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.ipynb"))
MAX_WORDS, MAX_CELL_WORDS = 4_500, 400  # a chapter fits a class period's reading; a cell a screen
MAX_SECTION_WORDS = 1_200


def markdown_cells(path: Path) -> list[str]:
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    return ["".join(c["source"]) for c in cells if c["cell_type"] == "markdown"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_chapter_reads_as_a_lesson_of_bounded_length(path):
    words = [len(text.split()) for text in markdown_cells(path)]
    assert sum(words) <= MAX_WORDS, f"{path.name}: {sum(words)} markdown words"
    longest = max(range(len(words)), key=words.__getitem__)
    assert words[longest] <= MAX_CELL_WORDS, (
        f"{path.name}: markdown cell {longest} has {words[longest]} words; split or tighten it")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_no_section_outgrows_a_sitting(path):
    """A ``##`` section is read in one go; the course's investigations live in RESULTS.md."""
    words, section = {}, "before the first section"
    for text in markdown_cells(path):
        section = next((line for line in reversed(text.splitlines()) if line.startswith("## ")),
                       section)
        words[section] = words.get(section, 0) + len(text.split())
    longest = max(words, key=words.get)
    assert words[longest] <= MAX_SECTION_WORDS, f"{path.name}: {longest!r}: {words[longest]} words"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_chapter_opens_with_the_paper_and_its_time(path):
    first = markdown_cells(path)[0]
    assert "arXiv:2602.03604" in first
    assert "**Study time:**" in first and "**Compute time**" in first


def test_readme_is_a_landing_page():
    """The README is where a teacher or learner starts: short, with the learner path up front."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    assert len(text.split()) < 1_300, "move detail to RESULTS.md, TEACHING.md or docs/running.md"
    assert "## The learner path" in text and "make lab-student" in text
    assert "**Teaching a class?**" in text and "TEACHING.md" in text
