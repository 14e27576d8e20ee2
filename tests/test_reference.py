"""Reference figures: what benchmarks record and notebooks print beside a learner's run."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from ebjepa_tutorial.course import reference
from tools import figures as figs

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
ROOT = NOTEBOOKS.parent
USED = re.compile(r"reference\.(?:compare|show)\(\s*\"(\w+)\"")


def notebook_code(path: Path) -> str:
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    return "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")


def test_record_keeps_other_figures_and_compare_prints_all_three(tmp_path):
    path = tmp_path / "reference.json"
    figs.record("vicreg_probe_acc", 0.554, "python b.py --record", "2,000 steps", 2, path)
    figs.record("world_probe_px", 1.063, "python c.py --record", "probe", 2, path)
    assert set(reference.load(path)) == {"vicreg_probe_acc", "world_probe_px"}
    line = reference.compare("vicreg_probe_acc", 0.5512, scale="class", path=path)
    assert line.startswith("linear probe accuracy: this notebook 55.1% | the course's class run "
                           "55.4% (2 CPU threads, ")
    assert line.endswith("| the paper 90.1% (ResNet-18, 300 epochs on a GPU, its probe trained "
                         "online on augmented views)")
    assert "smoke test" in reference.compare("vicreg_probe_acc", 0.1, scale="ci", path=path)
    assert reference.compare("world_probe_px", path=path).startswith(
        "position probe error: the course's class run 1.06 px")
    figs.record("world_probe_px", 1.063, "python c.py --record", "probe", 1, path)
    assert "(1 CPU thread, " in reference.compare("world_probe_px", path=path)


def test_a_missing_figure_names_the_benchmark_that_records_it(tmp_path):
    line = reference.compare("planning_success_class", 0.3, "class", tmp_path / "none.json")
    assert "not recorded (run python -m research.benchmarks.planning --record)" in line
    with pytest.raises(KeyError, match="unknown reference key"):
        figs.record("made_up", 1.0, "", "", 2, tmp_path / "r.json")


def test_compare_prints_a_recorded_range_and_the_date(tmp_path):
    """A figure recorded over seeds prints its range beside the value, in the metric's own
    format, with the threads and the date it was measured."""
    path = tmp_path / "reference.json"
    figs.record("video_map_class_K4", 0.5181, "python v.py --record", "3 seeds", 2, path,
                spread=(0.5043, 0.5351), date="2026-01-02")
    line = reference.compare("video_map_class_K4", scale="class", path=path)
    assert ("the course's class runs, mean of 3 seeds 0.518 (range 0.504 to 0.535, 2 CPU "
            "threads, 2026-01-02)") in line


def test_only_a_learners_ci_figure_is_called_a_smoke_test_and_only_a_benchmark_is_named(
        tmp_path):
    """The ci warning is about the learner's own figure: a line printing only the references
    has none. A figure no benchmark records (its notebook prints it) is left out when it is
    missing, rather than sending the reader to run a command that does not exist."""
    missing = tmp_path / "none.json"
    assert "smoke test" not in reference.compare("vicreg_probe_acc", scale="ci", path=missing)
    assert "smoke test" in reference.compare("vicreg_probe_acc", 0.3, scale="ci", path=missing)
    assert reference.METRICS["video_ap3_lead"].benchmark is None
    line = reference.compare("video_ap3_lead", 0.1, scale="class", path=missing)
    assert line == "AP three steps ahead, K = 4 minus K = 1: this notebook 0.10"


def test_the_papers_figures_agree_with_the_paper_column_of_the_results_page():
    """RESULTS.md sets the course's figures beside the paper's, in each table's last column;
    the paper's figures are also typed into reference.METRICS, which the notebooks print. On
    every row that marks a figure with a paper value, that value, in the metric's format, is
    among the last column's numbers: two copies of one figure must not drift apart (nor a
    Table 4 value move to the wrong ablation)."""
    with_paper = {k for k, m in reference.METRICS.items() if m.paper is not None}
    checked = 0
    lines = (ROOT / "RESULTS.md").read_text(encoding="utf-8").splitlines()
    for row in [line for line in lines if line.startswith("|")]:  # the tables' rows
        last_column = row.strip().strip("|").split("|")[-1]
        for key in {m[1] for m in figs.FIGURE.finditer(row)} & with_paper:
            metric = reference.METRICS[key]
            numbers = re.findall(r"\d[\d.]*%?", last_column)
            assert metric.fmt.format(metric.paper) in numbers, (key, row)
            checked += 1
    assert checked >= 8  # the probes, the detection mAP, planning and the four ablations


@pytest.mark.parametrize("chapter", ["01", "02", "03", "05", "06"])
def test_chapter_prints_its_result_beside_the_references(chapter):
    (path,) = NOTEBOOKS.glob(f"{chapter}_*.ipynb")
    keys = USED.findall(notebook_code(path))
    assert any(f"reference.compare(\"{key}\"" in notebook_code(path) for key in keys), (
        f"{path.name} has no cell printing reference.compare(...) beside its result")
    assert set(keys) <= set(reference.METRICS)


def test_every_figure_a_notebook_prints_has_been_recorded():
    keys = {key for path in NOTEBOOKS.glob("*.ipynb") for key in USED.findall(notebook_code(path))}
    recorded = reference.load()
    missing = [key for key in sorted(keys)
               if reference.METRICS[key].benchmark and key not in recorded]
    assert not missing, f"run the benchmarks with --record for {missing}"
    for key in keys & set(recorded):  # a benchmark's figure names its --record run
        assert recorded[key]["command"] and recorded[key]["threads"] >= 1
        assert "--record" in recorded[key]["command"] or not reference.METRICS[key].benchmark


# ---- every figure in the course's prose comes from reference.json ----------------------------


def test_every_marked_figure_in_the_pages_agrees_with_the_recorded_one():
    wrong = figs.check_pages()
    assert not wrong, ("figures disagree with checkpoints/reference.json; run `python -m "
                       "tools.figures render`:\n" + "\n".join(wrong))


def test_the_results_page_and_the_readme_take_their_headlines_from_the_record():
    root = Path(__file__).resolve().parents[1]
    for page, keys in (("README.md", {"vicreg_probe_acc", "sigreg_probe_acc", "video_map_class_K4",
                                      "planning_success_shipped_fresh", "planning_success_live"}),
                       ("RESULTS.md", {"vicreg_shipped_probe_acc", "video_map_long_K4",
                                       "world_probe_px", "beyond_three_rooms_two_level"})):
        marked = {m[1] for m in figs.FIGURE.finditer((root / page).read_text())}
        assert keys <= marked, f"{page} types {sorted(keys - marked)} instead of marking them"


def test_a_planted_mismatch_is_caught_and_render_repairs_it(tmp_path):
    figures = {"vicreg_probe_acc": {"value": 0.6256},
               "planning_success_shipped_fresh": {"value": 0.9725, "spread": [0.951, 0.985]},
               "world_probe_px": {"value": 2.4444, "spread": [2.3, 2.61]}}
    text = ("VICReg <!--fig:vicreg_probe_acc-->62.6%<!--/fig--> and the planner "
            "<!--fig:planning_success_shipped_fresh:spread-->95.1-98.5%<!--/fig-->, "
            "probe <!--fig:world_probe_px:spread-->2.30-2.61 px<!--/fig-->")
    assert figs.mismatches(text, figures) == []
    planted = text.replace("62.6%", "63.6%")  # a figure typed by hand, and wrong
    assert figs.mismatches(planted, figures) == [
        "vicreg_probe_acc: written '63.6%', recorded '62.6%'"]
    assert figs.render(planted, figures) == text
    unknown = "<!--fig:made_up-->1<!--/fig-->"  # a misspelt marker: fix it, no run records it
    assert "unknown figure key 'made_up': fix the marker" in figs.mismatches(unknown, figures)[0]
    unrecorded = {k: v for k, v in figures.items() if k != "vicreg_probe_acc"}
    assert "record it first" in figs.mismatches(text, unrecorded)[0]
    no_spread = "<!--fig:vicreg_probe_acc:spread-->60-63%<!--/fig-->"
    assert "has no recorded spread" in figs.mismatches(no_spread, figures)[0]


def test_render_pages_rewrites_only_the_figures_and_keeps_a_notebooks_layout(tmp_path):
    (tmp_path / "checkpoints").mkdir()
    figures = {"world_probe_px": {"value": 2.4444}}
    (tmp_path / "checkpoints" / "reference.json").write_text(json.dumps(figures))
    (tmp_path / "notebooks").mkdir()
    source = NOTEBOOKS / "04_two_rooms_world.ipynb"
    notebook = json.loads(source.read_text(encoding="utf-8"))
    cell = notebook["cells"][0]["source"]  # a list of lines, each but the last ending in \n
    cell[:] = [figs.FIGURE.sub(lambda m: m[3], line) for line in cell]  # its own figures unmarked
    cell[-1] += "\n"
    cell.append("probe <!--fig:world_probe_px-->9.99 px<!--/fig-->")
    page = tmp_path / "notebooks" / source.name
    page.write_text(json.dumps(notebook, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    before = page.read_text(encoding="utf-8")
    (tmp_path / "README.md").write_text("<!--fig:world_probe_px-->1 px<!--/fig-->\n")
    path = tmp_path / "checkpoints" / "reference.json"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(reference, "REFERENCE_FILE", path)
        mp.setattr(reference.load, "__defaults__", (path,))
        assert len(figs.check_pages(tmp_path)) == 2
        assert figs.render_pages(tmp_path) == [tmp_path / "README.md", page]
        assert figs.check_pages(tmp_path) == []
    assert page.read_text(encoding="utf-8") == before.replace("9.99 px", "2.44 px")
    assert (tmp_path / "README.md").read_text() == "<!--fig:world_probe_px-->2.44 px<!--/fig-->\n"


# ---- nothing a run measures is typed into a notebook's text --------------------------------

# What notebook markdown may type: constants of the method, the world or an exercise, arithmetic
# on them, and the paper's own figures. A figure a run measures is marked (or printed by a cell).
CONSTANTS = {
    "01": {"10%",  # chance on ten classes
           "20%", "100%",  # the crops' area range
           "8 px", "16 px", "32 px",  # view, crop and image sizes
           "90%", "90.1%", "91.0%"},  # the paper
    "02": {"0.01",  # the sweep's smallest multiplier
           "16 px", "32 px", "90.1%", "91.0%"},
    "04": {"0%", "100%",  # where the textbook interval breaks down
           "0.5 px", "1 px", "1.3 px", "1.5 px", "1.8 px", "2 px", "4 px", "4.5 px",  # the world
           "35%",  # the data policy's door starts
           "97%"},  # the paper
    "05": {"1%", "61%", "89%", "97%",  # the paper's Tables
           "1.8 px", "15%",  # the data's largest step, the recipe's still steps
           "8%"},  # a class run's share of the paper's frames
    "06": {"0%", "100%",  # the wall test's ends
           "0.005",  # an exercise's temperature
           "0.05 px",  # MIN_STD, the spread's floor
           "1.8 px", "2 px", "2 s", "3.5 px", "4.5 px", "40 px",  # the world, the budget
           "11%", "60%",  # the interval of 3 in 10, worked in the text
           "15%", "40%",  # the refit's still steps, the long run's decay
           "95%", "97%"},  # the interval's level, the paper
    "07": {"0.1 px", "150 px", "10 px",  # the head's tolerance, cap and COST_SCALE
           "1.5 px", "1.8 px", "2 px", "4.5 px", "7.2 px", "29 px",  # steps, reach, spreads
           "95%"},  # the interval's level
}


def test_a_typed_figure_is_found_outside_markers_maths_and_code():
    text = ("Trains in 9 minutes to 62.5%, <!--fig:vicreg_probe_acc-->62.5%<!--/fig--> marked; "
            "$x = 3\\%$ and `lr=0.005` are not prose; a nine-minute run; mAP 0.526.")
    assert figs.typed_figures(text) == ["9 minutes", "62.5%", "nine-minute", "0.526"]


@pytest.mark.parametrize("path", sorted(NOTEBOOKS.glob("*.ipynb")), ids=lambda p: p.name[:2])
def test_a_notebooks_text_types_no_figure_a_run_measures(path):
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    typed = {figure for cell in cells if cell["cell_type"] == "markdown"
             for figure in figs.typed_figures("".join(cell["source"]))}
    allowed = CONSTANTS.get(path.name[:2], set())
    assert not typed - allowed, (
        f"{path.name} types {sorted(typed - allowed)}: mark a measured figure "
        "<!--fig:KEY-->...<!--/fig--> (checkpoints/reference.json) or print it from a cell; "
        "a constant of the method or a paper's figure goes into CONSTANTS with why")
    assert not allowed - typed, f"CONSTANTS lists {sorted(allowed - typed)}, no longer in the text"


# What README, RESULTS, TEACHING and docs/ may type outside markers: no figure a run measures.
_PAPER = {"0.607", "90.1%", "91.0%", "97%", "96%", "89%", "47%", "46%", "61%", "1%"}
PAGE_CONSTANTS = {
    "README.md": {"0.61", "0.607", "90.1%", "91.0%", "97%",  # the paper (0.607: its code)
                  "1 h",  # a study time (a plan, like the session plans)
                  "4.5 px", "95%"},  # success radius, interval level
    "RESULTS.md": _PAPER - {"89%"} | {
        "0.61", "0.38", "0.20",  # its K = 4 mAP; its K = 1 mAP and lead, read from its figure
        "10 minutes", "60%", "70%",  # a class period, and the thresholds the runs pass
        "0.05", "1.5 px", "1.8 px", "2 px", "4.5 px", "35%",  # the settings and the world
        "15%",  # the course recipe's still steps
        "95%"},
    "TEACHING.md": _PAPER - {"46%", "47%", "61%"} | {
        "5 min", "10 min", "15 min", "20 min", "25 min", "10 minutes", "45 minutes",
        "90 minutes",  # the session plans
        "0.61",  # the paper's K = 4 mAP (0.607: its code release)
        "4.5 px", "2 px", "0.05 px", "35%", "15%",  # success radius, spreads, data, recipe
        "0.5 px", "3.6 px", "16 px", "32 px", "40 px", "1 px",  # exercises' settings, sizes
        "0 px",  # the replay's gap: zero by construction
        "0.001", "0.02",  # sweep points
        "0.01", "80%", "90%",  # what to look for (criteria, not outcomes)
        "0.45", "0.89", "0.97",  # the von Mises turns' mean cosines (exercise 3's maths)
        "0.02%", "0%", "100%", "95%"},  # the trapezoid's error, the interval's level and ends
    "docs/running.md": {"a minute", "10 minutes", "30 s"},  # the scales' and tests' budgets
    # a dated case study: its history comes from research/notes/2026-12-05-planning-log.md
    "docs/planning_appendix.md": {"22%", "90%", "53 minutes", "1.8 px",
                                  "3.5 px", "8 px", "4.5 px", "95%", "97%"},
}


@pytest.mark.parametrize("page", sorted(PAGE_CONSTANTS))
def test_a_pages_text_types_no_figure_a_run_measures(page):
    typed = set(figs.typed_figures((ROOT / page).read_text(encoding="utf-8")))
    allowed = PAGE_CONSTANTS[page]
    assert not typed - allowed, (
        f"{page} types {sorted(typed - allowed)}: mark a measured figure "
        "<!--fig:KEY-->...<!--/fig--> (checkpoints/reference.json) or say it without the "
        "number; a constant of the method or a paper's figure goes into PAGE_CONSTANTS with why")
    assert not allowed - typed, f"PAGE_CONSTANTS lists {sorted(allowed - typed)}, no longer there"


def test_every_page_is_checked_for_typed_figures():
    pages = {str(p.relative_to(ROOT)) for pattern in figs.PAGES if not pattern.endswith("ipynb")
             for p in ROOT.glob(pattern)}
    assert pages == set(PAGE_CONSTANTS)
