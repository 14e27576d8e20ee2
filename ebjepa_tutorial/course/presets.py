"""Each notebook's sizes at the scale ``EBJEPA_SCALE`` names: ``ci`` (it runs, in under a minute on
2 CPU cores), ``class`` (default: a real result in about 10 minutes) or ``full`` (the paper's)."""

import os
from dataclasses import dataclass, replace

from ..envs import MAX_STEP
from ..models.world import WORLD_CONFIGS
from ..planning import Habits, Noise, PlannerConfig
from ..training.image import ImageJEPAConfig, SIGReg
from ..training.video import VIDEO_CONFIGS, VideoJEPAConfig, ablation_configs
from ..training.world import ABLATABLE_TERMS, WorldTrainConfig, course_recipe, paper_recipe

SCALES = ("ci", "class", "full")


def current_scale(environ: dict[str, str] | None = None) -> str:
    """Return the scale named by ``EBJEPA_SCALE`` (``class`` when unset)."""
    environ = os.environ if environ is None else environ
    scale = environ.get("EBJEPA_SCALE", "").strip().lower() or "class"
    if scale not in SCALES:
        raise ValueError(f"EBJEPA_SCALE={scale!r} is not a scale; choose one of "
                         f"{', '.join(SCALES)} (for example `EBJEPA_SCALE=ci make lab`).")
    return scale


@dataclass(frozen=True)
class CollapsePreset:
    """Notebook 00: toy data and the tiny joint-embedding network trained on it."""

    n_points: int = 1024  # 2-D points in the toy data set
    embed_dim: int = 8  # D, the embedding size
    hidden: int = 64  # width of the MLP encoder
    steps: int = 600  # full-batch Adam steps per training run
    lr: float = 3e-3


@dataclass(frozen=True)
class ImagePreset:
    """Notebooks 01 and 02: the CIFAR-10 runs of the notebook's loss (01 VICReg, 02 SIGReg)."""

    config: ImageJEPAConfig  # the notebook's run; its sweeps and ablations use dataclasses.replace
    long_config: ImageJEPAConfig  # the longer run they load (shipped at class; full: config)
    train_images: int = 50_000  # CIFAR-10 train images used to train and to fit the probe
    test_images: int = 10_000  # CIFAR-10 test images the probe and kNN are scored on
    sweep_steps: int = 500  # steps per run of notebook 02's sweeps and ablations


@dataclass(frozen=True)
class VideoPreset:
    """Notebook 03: the video JEPA run on Moving MNIST, its K ablation and the evaluation sizes."""

    train: VideoJEPAConfig  # the main run (K = 4, seed 0); the ablation changes K and the seed
    long_config: VideoJEPAConfig  # trained longer (shipped at class; full: `train`)
    rollout_steps: tuple[int, ...] = (1, 2, 4, 8)  # the K of the ablation (the paper's Figure 4b)
    seeds: tuple[int, ...] = (0, 1, 2)  # training seeds per K: other clips, other initial weights
    n_train_digits: int = 8000  # of the 10,000 MNIST test digits; the other 2,000 are held out
    n_probe: int = 500  # clips of training digits that the detection probe is fitted on
    n_eval: int = 500  # clips of held-out digits that AP is measured on
    horizons: int = 7  # AP 1..7 steps ahead, as in the paper
    probe_steps: int = 400  # Adam steps of the detection probe
    decoder_steps: int = 500  # Adam steps of the decoder that draws pictures of latents

    def long_runs(self, rollout_steps=None, seeds=None) -> list[VideoJEPAConfig]:
        """The long run at each K and seed (default: K = 1 and the main run's, its seed)."""
        return ablation_configs(self.long_config, rollout_steps or (1, self.train.rollout_steps),
                                seeds or (self.train.seed,))


@dataclass(frozen=True)
class TwoRoomsWorldPreset:
    """Notebook 04: how much of the Two Rooms world to generate and look at (no training)."""

    n_trajectories: int = 4096  # data-policy trajectories for the statistics and figures
    steps: int = 16  # actions per trajectory: 17 frames, the paper's training clips
    n_episodes: int = 200  # evaluation episodes for the random-policy baseline
    episode_steps: int = 200  # steps per evaluation episode, as in the paper


@dataclass(frozen=True)
class WorldModelPreset:
    """Notebook 05: the world-model training run, and how much we evaluate it on."""

    train: WorldTrainConfig  # the run; the no-inverse-dynamics ablation changes only its coeffs
    n_probe: int = 1000  # fresh 17-frame trajectories the position probe is fitted on
    n_test: int = 200  # held-out trajectories for probe errors and open-loop rollouts
    horizon: int = 32  # actions per held-out trajectory: how far rollouts go (training: K = 8)
    n_layouts: int = 64  # layouts x dot positions for the "dot or walls?" variance split
    n_positions: int = 32


@dataclass(frozen=True)
class LongerRuns:
    """Notebook 06's section 9: longer runs (shipped at class; None: the preset's world)."""

    paper: WorldTrainConfig | None = None  # experiment 3: the paper's recipe, longer, more data
    ablations: tuple[str, ...] = ()  # loss terms whose ablation is also trained like `paper`
    n_ablation: int = 20  # episodes (the first seeds of the list) per long-trained ablation
    course: WorldTrainConfig | None = None  # experiment 5: chapter 05's recipe, longer, wider


@dataclass(frozen=True)
class PlanningPreset:
    """Notebook 06: which saved world models plan, with which planner, on how many episodes."""

    world: WorldTrainConfig  # notebook 05's run; the ablations change only its coefficients
    run: str  # its file name (shipped at class: every scale but full plans with those models)
    planner: PlannerConfig  # MPPI with the summed cost; CEM and "last" change one field
    n_episodes: int = 100  # seeds first_seed.. for the main success rate
    n_compare: int = 20  # episodes (the first seeds of the same list) per other planner / model
    episode_batch: int = 10  # episodes the main runs play at once (a CPU's cache likes few)
    episode_steps: int = 200  # the paper's step budget
    first_seed: int = 10_000
    n_wall_test: int = 400  # fresh data-policy trajectories for the one-step wall test
    longer: LongerRuns = LongerRuns()  # the optional section 9's models


@dataclass(frozen=True)
class TwoLevelPreset:
    """Notebook 07's two-level planner (its ``TwoLevel``)."""

    low: PlannerConfig  # the lower level: a few steps to the subgoal
    high: tuple[PlannerConfig, PlannerConfig]  # the coarse level, in Two and Three Rooms
    lookahead: int = 2  # the subgoal: the coarse plan's latent this many coarse steps ahead
    reach_px: float = 4.5  # the final approach: the goal is the subgoal once the plan reaches it


@dataclass(frozen=True)
class BeyondPreset:
    """Notebook 07: the shipped models of two worlds (at every scale), four planners on each."""

    two_rooms: WorldTrainConfig  # chapter 05's class run
    three_rooms: WorldTrainConfig  # the same recipe on Three Rooms in a row
    flat: PlannerConfig  # chapter 06's class MPPI, its first spread 1.5 px as when measured
    short: PlannerConfig  # the same at a short horizon, latent distance
    learned: PlannerConfig  # `short` with the learned cost, in px: a temperature of 1
    two_level: TwoLevelPreset
    n_episodes: int = 40  # per planner and world
    first_seed: int = 10_000
    episode_batch: int = 10
    episode_steps: int | None = None  # None: each world's step budget (200 and 120 steps)


def image_preset(scale: str, loss: str) -> ImagePreset:
    """The preset of notebook 01 (``loss="vicreg"``) or 02 (``"sigreg"``) at ``scale``."""
    config, sigreg = _IMAGE[scale]
    config = replace(config, **sigreg) if loss == "sigreg" else config
    if scale == "ci":
        return ImagePreset(config, replace(config, steps=30), train_images=2000, test_images=1000,
                           sweep_steps=5)
    if scale == "class":  # the shipped long runs: the same recipe, 7.5 times longer
        return ImagePreset(config, replace(config, steps=12_000, warmup_steps=1200),
                           sweep_steps=250)
    return ImagePreset(config, config)


def course_long(config: WorldTrainConfig, steps: int, n_trajectories: int) -> WorldTrainConfig:
    """``config``'s recipe trained longer: a predictor twice as wide, the rate falling to 0 over
    the last 40% and every update's gradient clipped to norm 1."""
    model = replace(config.model, predictor_hidden=2 * config.model.predictor_hidden)
    recipe = replace(config.recipe, decay_steps=steps * 2 // 5, grad_clip=1.0)
    return replace(config, model=model, recipe=recipe, steps=steps, n_trajectories=n_trajectories)


_IMAGE = {  # chapter 01's run at each scale, and chapter 02's changes to it
    "ci": (ImageJEPAConfig(widths=(8, 8, 16, 16), blocks_per_stage=1, projector=(64, 64),
                           batch_size=32, steps=15, warmup_steps=3, eval_image_size=16),
           dict(loss=SIGReg(), projector=(64, 16))),  # narrower than VICReg's, as at class
    # about 10 minutes on 2 cores with bf16 instructions, about 30 in float32 on AVX2 only
    "class": (ImageJEPAConfig(widths=(32, 64, 128, 256), blocks_per_stage=1, steps=1600,
                              warmup_steps=160),
              dict(loss=SIGReg(0.05, slices=1024), projector=(1024, 256))),
    "full": (ImageJEPAConfig(  # the paper's network and 300 epochs of batch 256, all at 32 px
        widths=(64, 128, 256, 512), image_size=32, projector=(2048, 2048), batch_size=256,
        steps=300 * 195, warmup_steps=10 * 195),
             dict(loss=SIGReg(10.0, scale_by_n=False), projector=(2048, 128))),  # the paper's
}

_WORLD_CI = course_recipe(WorldTrainConfig(model=WORLD_CONFIGS["ci"], n_trajectories=500,
                                           batch_size=16, steps=10))
_WORLD_CLASS = course_recipe(WorldTrainConfig(steps=2800))  # 9-15 min on 2 cores; shipped
_WORLD_FULL = WorldTrainConfig(  # the paper: batch 384, 12 epochs of 100,000 trajectories
    model=WORLD_CONFIGS["full"], n_trajectories=100_000, batch_size=384, steps=12 * 100_000 // 384)
_PLANNER_CI = PlannerConfig(horizon=8, samples=32, elites=4, iterations=2, execute=4)

# Chapter 07's planners. The bound and spread of a macro-action scale with CoarseModel's
# stride; the fine planners keep the spread chapter 07 was measured with (1.5 px).
_STRIDE = 4
_FLAT_07 = PlannerConfig(noise=Noise(std=1.5))
_SHORT = replace(_FLAT_07, horizon=16, samples=100, elites=10)
_TINY = PlannerConfig(horizon=4, samples=16, elites=2, iterations=2, execute=4)
_HIGH = PlannerConfig(horizon=16, samples=50, elites=5, execute=1,
                      noise=Noise(std=_STRIDE * 1.5, period=2, bound=_STRIDE * MAX_STEP),
                      habits=Habits(warm_iterations=2, stop_px=0))
_BEYOND_CLASS = BeyondPreset(
    _WORLD_CLASS, replace(_WORLD_CLASS, walls=2), flat=_FLAT_07, short=_SHORT,
    learned=replace(_SHORT, cost="learned", temperature=1.0), two_level=TwoLevelPreset(
        low=replace(_FLAT_07, horizon=8, samples=50, elites=5, execute=_STRIDE,
                    habits=Habits(warm_iterations=2)),
        high=(_HIGH, replace(_HIGH, horizon=24, samples=200, elites=20,
                             habits=replace(_HIGH.habits, warm_iterations=3)))))
_BEYOND_CI = replace(  # the class models with tiny planners
    _BEYOND_CLASS, flat=_PLANNER_CI, short=_TINY,
    learned=replace(_TINY, cost="learned", temperature=1.0),
    two_level=TwoLevelPreset(_TINY, (replace(_HIGH, horizon=4, samples=16, elites=2),) * 2),
    n_episodes=2, episode_batch=2, episode_steps=24)

# the shipped checkpoints, with episode counts sized to fit a class period
_PLANNING_CLASS = PlanningPreset(
    _WORLD_CLASS, "world_model_class", PlannerConfig(), n_episodes=40, n_compare=10,
    longer=LongerRuns(paper=paper_recipe(replace(_WORLD_CLASS, steps=10_000,
                                                 n_trajectories=100_000)),
                      ablations=ABLATABLE_TERMS, course=course_long(_WORLD_CLASS, 10_000, 100_000)))

PRESETS: dict[str, dict[str, object]] = {
    "00": {"ci": CollapsePreset(n_points=256, steps=60),
           "class": CollapsePreset(),
           "full": CollapsePreset(n_points=4096, steps=2000)},
    "01": {scale: image_preset(scale, "vicreg") for scale in SCALES},
    "02": {scale: image_preset(scale, "sigreg") for scale in SCALES},
    "03": {"ci": VideoPreset(VIDEO_CONFIGS["ci"], replace(VIDEO_CONFIGS["ci"], steps=30),
                             seeds=(0,), n_probe=32, n_eval=32, probe_steps=20, decoder_steps=40),
           "class": VideoPreset(VIDEO_CONFIGS["class"],
                                replace(VIDEO_CONFIGS["class"], n_clips=24_000, steps=12_000)),
           "full": VideoPreset(VIDEO_CONFIGS["full"], VIDEO_CONFIGS["full"], n_probe=2000,
                               n_eval=2000, probe_steps=2000, decoder_steps=5000)},
    "04": {"ci": TwoRoomsWorldPreset(n_trajectories=512, n_episodes=32),
           "class": TwoRoomsWorldPreset(),
           "full": TwoRoomsWorldPreset(n_trajectories=100_000, n_episodes=1000)},
    "05": {"ci": WorldModelPreset(_WORLD_CI, n_probe=100, n_test=32, horizon=16, n_layouts=16,
                                  n_positions=16),
           "class": WorldModelPreset(_WORLD_CLASS),  # exactly the CLI's run (shipped)
           "full": WorldModelPreset(_WORLD_FULL, n_probe=5000, n_test=1000, horizon=48)},
    "06": {"ci": replace(_PLANNING_CLASS, planner=_PLANNER_CI, n_episodes=4, n_compare=2,
                         episode_steps=40, n_wall_test=100,
                         longer=replace(_PLANNING_CLASS.longer, n_ablation=2)),
           "class": _PLANNING_CLASS,
           # the reference code's planner on 500 episodes: 100 for the headline rate, 50 in 8 rows
           "full": PlanningPreset(_WORLD_FULL, "world_model_full", PlannerConfig(
               horizon=90, iterations=20, execute=1, noise=Noise(period=1),
               habits=Habits(0, stop_px=0.0)), n_episodes=100, n_compare=50, episode_batch=100)},
    "07": {"ci": _BEYOND_CI,
           "class": _BEYOND_CLASS,  # the world models, heads and coarse models are shipped
           "full": replace(_BEYOND_CLASS, n_episodes=200, episode_batch=100)},
}


def preset(notebook: str, scale: str | None = None):
    """Return the sizes for ``notebook`` (e.g. ``"00"``) at ``scale`` (default: current)."""
    if notebook not in PRESETS:
        raise KeyError(f"no presets for notebook {notebook!r}; known: {', '.join(PRESETS)} "
                       "(two-digit strings)")
    if scale is not None and scale not in SCALES:  # the argument, not the environment's
        raise ValueError(f"scale must be one of {', '.join(SCALES)}, or None for "
                         f"EBJEPA_SCALE's; got {scale!r}")
    return PRESETS[notebook][scale or current_scale()]
