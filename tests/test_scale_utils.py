"""The presets switch, seeding and device choice, precision and the config checks' rules."""

import random
from dataclasses import dataclass, replace
from operator import attrgetter

import numpy as np
import pytest
import torch

from ebjepa_tutorial import utils
from ebjepa_tutorial.course import presets
from ebjepa_tutorial.envs.episodes import THREE_ROOMS_EPISODE_STEPS
from ebjepa_tutorial.planning import PlannerConfig
from ebjepa_tutorial.utils import as_generator, get_device, seed_everything


def test_default_scale_is_class():
    assert presets.current_scale({}) == "class"
    assert presets.current_scale({"EBJEPA_SCALE": ""}) == "class"


@pytest.mark.parametrize("name", ["ci", "class", "full", " CI "])
def test_known_scales(name):
    assert presets.current_scale({"EBJEPA_SCALE": name}) == name.strip().lower()


def test_unknown_scale_names_the_choices():
    with pytest.raises(ValueError, match="ci, class, full"):
        presets.current_scale({"EBJEPA_SCALE": "huge"})


def test_preset_follows_the_environment(monkeypatch):
    monkeypatch.setenv("EBJEPA_SCALE", "ci")
    assert presets.preset("00") == presets.PRESETS["00"]["ci"]
    assert presets.preset("00", "full").steps > presets.preset("00", "class").steps
    with pytest.raises(KeyError, match="no presets"):
        presets.preset("99")


def test_every_preset_has_every_scale():
    for notebook, by_scale in presets.PRESETS.items():
        assert set(by_scale) == set(presets.SCALES), notebook


def test_same_seed_same_numbers():
    a = torch.randn(5, generator=seed_everything(3))
    b = torch.randn(5, generator=seed_everything(3))
    c = torch.randn(5, generator=as_generator(4))
    assert torch.equal(a, b) and not torch.equal(a, c)
    seed_everything(7)
    x = torch.rand(3)
    seed_everything(7)
    assert torch.equal(x, torch.rand(3))


def test_seed_must_be_an_integer():
    with pytest.raises(TypeError, match="seed must be an int"):
        seed_everything(1.5)


def test_seed_everything_seeds_python_and_numpy_too():
    """Notebook code draws from random and numpy.random as well as torch: after the same seed
    each gives the same numbers again, also for a seed past numpy's 2**32 limit."""
    for seed in (3, 2**40 + 3):
        seed_everything(seed)
        first = (random.random(), np.random.rand(), torch.rand(1).item())
        seed_everything(seed)
        assert (random.random(), np.random.rand(), torch.rand(1).item()) == first, seed


def test_as_generator_hands_a_generator_back_itself_and_refuses_a_bool():
    """A torch.Generator passed on is used as it stands (its stream goes on, not restarts);
    True is an int to Python but no seed anyone means."""
    generator = torch.Generator().manual_seed(5)
    torch.rand(3, generator=generator)
    assert as_generator(generator) is generator
    with pytest.raises(TypeError, match="seed must be an int"):
        as_generator(True)


def test_a_numpy_number_is_told_to_become_a_python_one():
    """np.int64(5) reads as an int to a learner; the messages say what it is and the remedy."""
    with pytest.raises(TypeError, match=r"got int64 \(NumPy's\): pass int\(seed\)"):
        as_generator(np.int64(3))
    with pytest.raises(ValueError, match=r"horizon must be an int >= 1, got np.int64\(5\); a "
                                         r"NumPy number: pass int\(\.\.\.\) or float"):
        PlannerConfig(horizon=np.int64(5))


@pytest.mark.parametrize("cuda, mps, best", [
    (True, True, "cuda"), (False, True, "mps"), (False, False, "cpu")])
def test_device_choice_prefers_cuda_then_mps_then_cpu(monkeypatch, cuda, mps, best):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: mps)
    assert get_device().type == best
    assert get_device("cpu") == torch.device("cpu")  # asked for, whatever is available


def test_video_preset_fits_its_clips_and_budget():
    for name in presets.SCALES:
        cfg = presets.preset("03", name)
        context = cfg.train.model.context
        assert cfg.train.rollout_steps in cfg.rollout_steps and cfg.train.seed in cfg.seeds
        assert cfg.train.n_frames >= context + max(cfg.rollout_steps), name  # the longest K fits
        assert cfg.train.n_frames >= context + cfg.horizons, name  # AP 1..horizons fits
        assert cfg.n_train_digits < 10_000  # some MNIST test digits are held out
    ci, class_ = presets.preset("03", "ci"), presets.preset("03", "class")
    assert set(class_.rollout_steps) >= {1, 2, 4} and len(class_.seeds) == 3
    # under 10 minutes per class run on 2 idle CPU cores (RESULTS.md, section 03)
    assert (class_.train.batch_size, class_.train.steps, class_.train.n_clips) == (16, 2400, 4000)
    assert ci.train.steps * ci.train.batch_size * len(ci.seeds) < 1000  # ci: seconds


_IMAGE_WORK = ("config.steps", "long_config.steps", "train_images", "test_images", "sweep_steps")
WORK = {  # the counts that set how long each notebook runs ("seeds": how many; None: 120 steps)
    "00": ("n_points", "steps"), "01": _IMAGE_WORK, "02": _IMAGE_WORK,
    "03": ("train.steps", "train.n_clips", "long_config.steps", "seeds", "n_probe", "n_eval",
           "probe_steps", "decoder_steps"),
    "04": ("n_trajectories", "n_episodes"),
    "05": ("train.steps", "train.n_trajectories", "n_probe", "n_test", "n_layouts"),
    "06": ("n_episodes", "n_compare", "episode_steps", "n_wall_test", "longer.n_ablation",
           "planner.samples", "planner.horizon"),
    "07": ("n_episodes", "episode_steps", "flat.samples", "short.samples",
           "two_level.low.samples"),
}


def _work(notebook, scale, path):
    value = attrgetter(path)(presets.preset(notebook, scale))
    if value is None:  # notebook 07's episodes: each world's step budget, 120 in Three Rooms
        return THREE_ROOMS_EPISODE_STEPS
    return len(value) if isinstance(value, tuple) else value


@pytest.mark.parametrize("notebook", sorted(WORK))
def test_ci_is_a_fraction_of_class_and_class_no_more_than_full(notebook):
    """ci is a smoke test (each notebook in about a minute on 2 cores, `make test` runs them
    all), class a class period's run, full the paper's: every count that sets how long a
    notebook runs is at most a third at ci of its class value, and no larger at class than at
    full. A ci count left at class's size, or a full one cut below class, breaks this."""
    assert set(WORK) == set(presets.PRESETS)
    for path in WORK[notebook]:
        ci, class_, full = (_work(notebook, scale, path) for scale in presets.SCALES)
        assert 3 * ci <= class_ <= full, (notebook, path, ci, class_, full)


@pytest.mark.parametrize("name", presets.SCALES)
def test_planning_uses_the_world_model_of_notebook_05(name):
    # Notebook 06 loads chapter 05's saved run by name, and trains none: the shipped class run
    # (and the shipped class runs of sections 7-9) at ci and class, notebook 05's own at full
    planning_preset = presets.preset("06", name)
    trained = "full" if name == "full" else "class"
    assert planning_preset.world == presets.preset("05", trained).train
    assert planning_preset.run == f"world_model_{trained}"
    if name == "ci":
        assert planning_preset.longer == replace(presets.preset("06", "class").longer,
                                                 n_ablation=planning_preset.longer.n_ablation)
    assert planning_preset.n_compare <= planning_preset.n_episodes
    assert planning_preset.longer.n_ablation <= planning_preset.n_episodes
    assert planning_preset.planner.horizon >= planning_preset.planner.execute


def test_time_parts_takes_the_median_of_each_part_after_a_warm_up(monkeypatch):
    from research.benchmarks import timing

    clock = iter(range(0, 1000, 1))  # each reading of the clock is one second later
    monkeypatch.setattr(timing.time, "perf_counter", lambda: next(clock))
    lengths = {0: (50, 50), 1: (1, 3), 2: (2, 5), 3: (9, 4)}  # the warm-up is slow

    def step(repeat):
        for name, extra in zip(("load", "train"), lengths[repeat]):
            for _ in range(extra - 1):
                next(clock)  # the part reads the clock extra - 1 times: it lasts `extra`
            yield name

    assert timing.time_parts(step, repeats=3) == {"load": 2, "train": 4}


def test_at_least_float32_raises_only_half_precisions():
    """bfloat16 and float16 outputs are raised to float32 before a loss's statistics; float32
    and float64 are left as they are (a float64 check must not lose its digits)."""
    for dtype, expected in ((torch.bfloat16, torch.float32), (torch.float16, torch.float32),
                            (torch.float32, torch.float32), (torch.float64, torch.float64)):
        assert utils.at_least_float32(torch.ones(2, dtype=dtype)).dtype == expected, dtype


@pytest.mark.parametrize("major, dtype", [(7, torch.float32), (8, torch.bfloat16),
                                          (9, torch.bfloat16)])
def test_a_cuda_gpu_computes_in_bfloat16_from_ampere_on(monkeypatch, major, dtype):
    """Compute capability 8 (Ampere, the A100) and later have native bfloat16; a Volta or
    Turing GPU (7) would only emulate it, slower than float32."""
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device=None: (major, 0))
    assert utils.network_dtype("cuda") == dtype


def test_the_check_predicates_refuse_bools_zero_and_infinity():
    """is_int_at_least, is_positive and is_non_negative: True is not a count, 0 is not
    positive, and an infinite or NaN number is neither positive nor non-negative."""
    at_least_one = utils.is_int_at_least(1)
    assert at_least_one(1) and not at_least_one(0) and not at_least_one(True)
    assert not at_least_one(2.0)
    assert utils.is_positive(0.5) and utils.is_positive(3)
    for bad in (0, 0.0, -1, True, float("inf"), float("nan")):
        assert not utils.is_positive(bad), bad
    assert utils.is_non_negative(0) and utils.is_non_negative(2.5)
    for bad in (-1e-9, False, float("inf"), float("nan")):
        assert not utils.is_non_negative(bad), bad


def test_check_fields_names_the_field_and_what_it_means():
    """The error names the class, the field, its meaning when the rule gives one, the rule and
    the value; a config that keeps every rule passes silently."""

    @dataclass
    class Config:
        steps: int = 10
        lr: float = 0.1

    rules = {"steps": (utils.is_int_at_least(1), "an int >= 1"),
             "lr": (utils.is_positive, "a number > 0", "the learning rate")}
    utils.check_fields(Config(), rules)
    with pytest.raises(ValueError, match=r"^Config\.lr \(the learning rate\) must be a number "
                                         r"> 0, got -0\.1$"):
        utils.check_fields(Config(lr=-0.1), rules)
    with pytest.raises(ValueError, match=r"^Config\.steps must be an int >= 1, got 0$"):
        utils.check_fields(Config(steps=0, lr=-0.1), rules)  # the first broken rule


@pytest.mark.parametrize("scale", ["small", "", "CI"])
def test_a_scale_passed_to_preset_is_checked_as_given(scale, monkeypatch):
    """The argument, not EBJEPA_SCALE, is wrong: the message says so (an empty one does not
    silently fall back to the environment's)."""
    monkeypatch.setenv("EBJEPA_SCALE", "ci")
    with pytest.raises(ValueError, match=r"scale must be one of ci, class, full, or None for "
                                         r"EBJEPA_SCALE's; got"):
        presets.preset("06", scale)
    assert presets.preset("06", None) == presets.preset("06", "ci")
