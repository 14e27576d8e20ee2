"""Maintainer commands (research/, tools/figures.py): what they refuse before any work, and what
they record. Nothing here writes under checkpoints/: records go to copies in tmp_path."""

from __future__ import annotations

import shutil
import sys
from types import SimpleNamespace

import pytest

from ebjepa_tutorial.course.reference import REFERENCE_FILE, load
from ebjepa_tutorial.training.checkpoints import SHIPPED_DIR
from tools import figures


def _usage_error(main, argv, capsys, monkeypatch=None) -> str:
    """``main``'s usage message (exit 2) for ``argv``: via ``sys.argv`` when ``monkeypatch``."""
    with pytest.raises(SystemExit) as done:
        if monkeypatch is None:
            main(argv)
        else:
            monkeypatch.setattr(sys, "argv", ["command", *argv])
            main()
    assert done.value.code == 2
    return capsys.readouterr().err


def test_a_record_without_a_spread_keeps_the_recorded_one(tmp_path):
    path = tmp_path / "reference.json"
    shutil.copy(REFERENCE_FILE, path)  # the real figures, never the real file
    spread = load(path)["world_train_min"]["spread"]  # printed by the pages as a range
    figures.record("world_train_min", 11.0, "python -m research.benchmarks.two_rooms --record",
                   "a new run", 2, path)
    stored = load(path)["world_train_min"]
    assert (stored["value"], stored["spread"]) == (11.0, spread)
    assert figures.figure_text("world_train_min", spread=True, figures=load(path))
    figures.record("world_train_min", 11.0, "c", "p", 2, path, spread=(10.0, 12.0))
    assert load(path)["world_train_min"]["spread"] == [10.0, 12.0]  # a new one replaces it


def test_beyond_records_its_command_line_and_only_the_recorded_size(monkeypatch, capsys):
    from research.benchmarks import beyond

    monkeypatch.setattr(beyond.torch, "set_num_threads", lambda n: None)  # this process's stay
    monkeypatch.setattr(beyond, "planners", lambda walls: pytest.fail("a model was loaded"))
    assert "200 episodes" in _usage_error(beyond.main, ["--record", "--episodes", "2"], capsys,
                                          monkeypatch)
    result = SimpleNamespace(success_rate=0.5, cpu_seconds_per_episode=1.0,
                             summary=lambda: "success 50%")
    monkeypatch.setattr(beyond, "planners", lambda walls: {"flat": (None, None, None)})
    monkeypatch.setattr(beyond, "run_episodes", lambda *args, **kwargs: result)
    recorded = {}
    monkeypatch.setattr(beyond.figures, "record",
                        lambda key, value, **where: recorded.update({key: where["command"]}))
    argv = ["--walls", "1", "--planners", "flat", "--first-seed", "5", "--record"]
    monkeypatch.setattr(sys, "argv", ["beyond.py", *argv])
    beyond.main()
    assert recorded == {"beyond_two_rooms_flat": "python -m research.benchmarks.beyond "
                                                 + " ".join(argv)}


def test_notebooks_cold_cache_moves_aside_the_cache_the_kernels_read(tmp_path, monkeypatch,
                                                                     capsys):
    from research.benchmarks import notebooks

    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "run.pt").write_bytes(b"x")
    with notebooks.cold_cache(True):
        assert not (tmp_path / "checkpoints").exists()
    assert (tmp_path / "checkpoints" / "run.pt").read_bytes() == b"x"
    monkeypatch.setattr(notebooks, "run_notebook", lambda *a: pytest.fail("a notebook ran"))
    _usage_error(notebooks.main, ["--only"], capsys, monkeypatch)  # a bare --only timed nothing


def test_train_image_refuses_zero_steps_before_loading_data(monkeypatch, capsys):
    from research import train_image

    monkeypatch.setattr(train_image, "load_cifar10", lambda split: pytest.fail("data loaded"))
    err = _usage_error(train_image.main, ["--steps", "0", "--out", "x.pt"], capsys)
    assert "--steps takes an int >= 1" in err


def test_planning_refuses_a_bad_planner_setting_and_a_model_of_another_world(monkeypatch,
                                                                            capsys):
    from research.benchmarks import planning

    monkeypatch.setattr(planning.torch, "set_num_threads", lambda n: None)  # this process's stay
    monkeypatch.setattr(planning, "run_episodes", lambda *a, **k: pytest.fail("it planned"))
    assert "invalid choice" in _usage_error(planning.main, ["--method", "foo"], capsys,
                                            monkeypatch)
    assert "invalid choice" in _usage_error(planning.main, ["--cost", "learned"], capsys,
                                            monkeypatch)
    three_rooms = str(SHIPPED_DIR / "world_model_three_rooms_class.pt")
    err = _usage_error(planning.main, ["--checkpoint", three_rooms, "--walls", "1"], capsys,
                       monkeypatch)
    assert "trained with --walls 2" in err
    err = _usage_error(planning.main, ["--checkpoint", str(SHIPPED_DIR / "world_model_class.pt"),
                                       "--walls", "2"], capsys, monkeypatch)
    assert "trained with --walls 1" in err


def test_train_world_refit_gives_usage_errors_not_tracebacks(monkeypatch, capsys, tmp_path):
    from research import train_world

    monkeypatch.setattr(train_world, "refit_predictor", lambda *a, **k: pytest.fail("it fit"))
    two_rooms = str(SHIPPED_DIR / "world_model_class.pt")
    err = _usage_error(train_world.main, ["--refit", two_rooms, "--out", "x.pt", "--steps", "0"],
                       capsys)
    assert "steps" in err
    three_rooms = str(SHIPPED_DIR / "world_model_three_rooms_class.pt")
    err = _usage_error(train_world.main, ["--refit", three_rooms, "--out", "x.pt"], capsys)
    assert "Two Rooms data only" in err
    err = _usage_error(train_world.main, ["--refit", str(tmp_path / "none.pt"), "--out", "x.pt"],
                       capsys)
    assert "no checkpoint at" in err and "none.pt" in err
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    err = _usage_error(train_world.main, ["--refit", str(tmp_path / "bad.pt"), "--out", "x.pt"],
                       capsys)
    assert "is damaged" in err


@pytest.mark.parametrize("variant", [["--tiny"], ["--set", "consistency=0"], ["--walks-only"]])
def test_fit_beyond_variants_refuse_the_shipped_folder(variant, monkeypatch, capsys):
    from research import fit_beyond

    monkeypatch.setattr(fit_beyond, "load_run", lambda *a, **k: pytest.fail("a model loaded"))
    monkeypatch.chdir(SHIPPED_DIR.parent)  # the documented spelling, relative to the root
    for folder in ("checkpoints", str(SHIPPED_DIR), "checkpoints/../checkpoints/"):
        err = _usage_error(fit_beyond.main, ["--world", "two_rooms", "--out-dir", folder,
                                             *variant], capsys)
        assert f"{variant[0]} would overwrite the shipped fits" in err


def test_resave_check_fails_when_a_shipped_identity_differs(monkeypatch, capsys):
    from ebjepa_tutorial.training.checkpoints import load_checkpoint
    from research import resave_checkpoints

    stored = load_checkpoint(SHIPPED_DIR / "world_model_class.pt")["config"]
    # a field only today's identity records: a re-save, not a refusal, would follow
    monkeypatch.setattr(resave_checkpoints, "shipped_runs",
                        lambda: {"world_model_class": {**stored, "new_field": 1}})
    monkeypatch.setattr(resave_checkpoints, "save_checkpoint",
                        lambda *a, **k: pytest.fail("--check wrote a file"))
    assert resave_checkpoints.main(["--check"]) == 1
    assert "differ from today's identity: world_model_class.pt" in capsys.readouterr().out
    monkeypatch.setattr(resave_checkpoints, "shipped_runs",
                        lambda: {"world_model_class": stored})
    assert resave_checkpoints.main(["--check"]) == 0
