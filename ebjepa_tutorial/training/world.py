"""The Two Rooms world model's training run (notebook 05 writes its loop): configs, recipes, the
step, latent replay, identities, and loading a saved run (notebooks 06 and 07 train none)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from .. import distributed
from ..envs import generate_trajectories
from ..envs.trajectories import Trajectories
from ..envs.two_rooms import WALL_X_RANGES
from ..losses.sigreg import sigreg
from ..losses.world import (
    WorldLossCoeffs,
    encode_for_loss,
    inverse_dynamics_loss,
    multistep_prediction_loss,
    temporal_similarity_loss,
    variance_covariance_loss,
)
from ..models.world import WORLD_CONFIGS, WorldConfig, WorldModel
from ..utils import get_device
from .checkpoints import checkpoint_paths, load_made_by, run_identity, step_identity
from .loop import load_or_train

TRAJECTORY_ACTIONS = 16  # per training trajectory (17 frames, the paper's clips)
WEIGHT_DECAY = 1e-5  # AdamW's, as in the paper
# each replayed update draws REPLAY_BATCH windows of the last REPLAY_CAPACITY, with its Adam
REPLAY_BATCH, REPLAY_CAPACITY, REPLAY_LR = 1024, 6400, 1e-3


@dataclass(frozen=True)
class Recipe:
    """How a run departs from the paper's training (notebook 05); the defaults are the paper's."""

    window: int = 0  # frames per training window at a random offset (0: whole trajectories)
    wall_fraction: float = 0.0  # share of trajectories that start heading into a wall
    stay_probability: float = 0.0  # share of imagined steps that are "still" (zero action)
    replay_steps: int = 0  # predictor updates (encoder frozen) on replayed latents per step
    channels_last: bool = False  # faster convolutions, but another order of float sums
    decay_steps: int = 0  # the last decay_steps lower the rate linearly towards 0 (0: constant)
    grad_clip: float = 0.0  # every update's gradient scaled to at most this norm (0: none)

    def __post_init__(self):
        if self.window and not 2 <= self.window <= TRAJECTORY_ACTIONS + 1:
            raise ValueError(f"Recipe.window={self.window} does not fit trajectories of "
                             f"{TRAJECTORY_ACTIONS + 1} frames: use 2..{TRAJECTORY_ACTIONS + 1} "
                             "frames, or 0 for whole trajectories")


@dataclass(frozen=True)
class WorldTrainConfig:
    """One training run of the world model. Defaults: the paper's recipe with the class model."""

    model: WorldConfig = field(default_factory=lambda: WORLD_CONFIGS["class"])
    coeffs: WorldLossCoeffs = field(default_factory=WorldLossCoeffs)  # the paper's weights
    recipe: Recipe = field(default_factory=Recipe)  # the paper's; course_recipe: the class run's
    n_trajectories: int = 20_000  # offline data set (the paper: 100,000 trajectories)
    walls: int = 1  # 1: Two Rooms (the paper's world); 2: Three Rooms in a row (chapter 07)
    batch_size: int = 64  # trajectories per step, global under torchrun (the paper: 384)
    steps: int = 1000
    lr: float = 1e-3  # AdamW, as in the paper
    rollout_steps: int = 8  # K, the prediction horizon of the loss (at most the window - 1)
    seed: int = 0

    def __post_init__(self):  # here, not at the first step after minutes of data generation
        frames = self.recipe.window or TRAJECTORY_ACTIONS + 1
        if not 1 <= self.rollout_steps < frames:
            raise ValueError(f"rollout_steps (K) must be 1..{frames - 1} for windows of {frames} "
                             f"frames (Recipe.window), got {self.rollout_steps}")


def course_recipe(config: WorldTrainConfig) -> WorldTrainConfig:
    """``config`` trained the course's way (the class preset): more per CPU-minute."""
    recipe = Recipe(window=9, wall_fraction=0.25, stay_probability=0.15, replay_steps=3,
                    channels_last=True)
    return replace(config, recipe=recipe, model=replace(config.model, predictor="mlp"))


def paper_recipe(config: WorldTrainConfig) -> WorldTrainConfig:
    """``config`` trained the paper's way: whole trajectories, a GRU predictor, no replay (its
    loss unrolled from the first frame, as the reference code does: ``losses.world``)."""
    return replace(config, recipe=Recipe(),
                   model=replace(config.model, predictor=WorldConfig.predictor))


def make_data(config: WorldTrainConfig) -> Trajectories:
    """The offline training trajectories of ``config`` (seeded by ``config.seed``)."""
    return generate_trajectories(config.n_trajectories, TRAJECTORY_ACTIONS, seed=config.seed,
                                 wall_fraction=config.recipe.wall_fraction, walls=config.walls)


class LatentReplay:
    """Predictor and action-encoder updates on the detached latents ``(B, T, D)`` and actions
    ``(B, T-1, A)`` of recent batches (:meth:`add`); ``replay(step)`` makes ``replay_steps``."""

    STREAM = 2**40  # the replay's generators: seeded apart from the batches' (step_generator)

    def __init__(self, model: WorldModel, config: WorldTrainConfig, frames: int, device):
        try:  # each rank replays its share of the draw, by the batch's own rule
            distributed.per_rank_batch(REPLAY_BATCH)
        except ValueError:
            raise ValueError(f"latent replay's {REPLAY_BATCH} windows per update cannot be "
                             f"shared by {distributed.world_size()} processes: run a power of "
                             "2 of them, or a recipe with replay_steps=0") from None
        self.model, self.config, self.filled, self.head = model, config, 0, 0
        self.parameters = [*model.predictor.parameters(), *model.action_encoder.parameters()]
        self.optimizer = torch.optim.Adam(self.parameters, lr=REPLAY_LR)
        self.latents = torch.zeros(REPLAY_CAPACITY, frames, model.latent_dim, device=device)
        self.actions = torch.zeros(REPLAY_CAPACITY, frames - 1, model.config.action_dim,
                                   device=device)

    def add(self, z: torch.Tensor, actions: torch.Tensor) -> None:
        z, actions = distributed.gather_rows(z.detach()), distributed.gather_rows(actions)
        rows = (self.head + torch.arange(len(z), device=z.device)) % len(self.latents)
        self.latents[rows], self.actions[rows] = z, actions
        self.head = (self.head + len(z)) % len(self.latents)
        self.filled = min(self.filled + len(z), len(self.latents))

    def __call__(self, step: int) -> None:
        config, recipe = self.config, self.config.recipe
        generator = torch.Generator().manual_seed(self.STREAM + config.seed * 1_000_003 + step)
        for group in self.optimizer.param_groups:  # the joint step's schedule
            group["lr"] = REPLAY_LR * decay_factor(config, step)
        for _ in range(recipe.replay_steps):
            pick = torch.randint(0, self.filled, (REPLAY_BATCH,), generator=generator)
            pick = distributed.local_rows(pick).to(self.latents.device)
            loss = multistep_prediction_loss(
                self.model.predict, self.latents[pick], self.actions[pick], config.rollout_steps,
                stay_probability=recipe.stay_probability, generator=generator,
                rand=distributed.rand_rows)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            distributed.average_gradients(self.parameters)
            if recipe.grad_clip:
                torch.nn.utils.clip_grad_norm_(self.parameters, recipe.grad_clip)
            self.optimizer.step()

    def state_dict(self) -> dict:
        return {"latents": self.latents, "actions": self.actions, "filled": self.filled,
                "head": self.head, "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.latents.copy_(state["latents"])
        self.actions.copy_(state["actions"])
        self.filled, self.head = int(state["filled"]), int(state["head"])
        self.optimizer.load_state_dict(state["optimizer"])


def new_model(config: WorldTrainConfig, data: Trajectories) -> WorldModel:
    """A fresh model, its input standardisation fitted on 256 of the trajectories."""
    torch.manual_seed(config.seed)
    return WorldModel(config.model).fit_input_stats(data.frames(slice(0, 256)))


def new_optimizer(model: WorldModel, config: WorldTrainConfig) -> torch.optim.AdamW:
    """AdamW on every parameter at ``config.lr``, with the paper's weight decay."""
    return torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=WEIGHT_DECAY)


def decay_factor(config: WorldTrainConfig, step: int) -> float:
    """Step ``step``'s share of the base rate: 1, then down to ``1 / decay_steps`` linearly."""
    decay = config.recipe.decay_steps
    return min(1.0, (config.steps - step) / decay) if decay else 1.0


# the names notebook 05's exercises give the two terms: there the learner's own functions
temporal_similarity, inverse_dynamics = temporal_similarity_loss, inverse_dynamics_loss


def world_model_step(model, optimizer, frames, actions, generator, config, step, replay=None):
    """One training step (notebook 05) on ``frames (B, T, 2, 65, 65)``, ``actions (B, T-1, 2)``:
    returns the detached total and terms."""
    z = encode_for_loss(model, frames)
    coeffs, recipe = config.coeffs, config.recipe
    terms = {
        "prediction": multistep_prediction_loss(
            model.predict, z, actions, config.rollout_steps,
            stay_probability=recipe.stay_probability, generator=generator,
            rand=distributed.rand_rows),
        "temporal": temporal_similarity(z),
        "inverse_dynamics": inverse_dynamics(model.predict_actions, z, actions),
    }
    everyone = distributed.gather_rows(z)
    terms["variance"], terms["covariance"] = variance_covariance_loss(everyone)
    if coeffs.sigreg:
        terms["sigreg"] = sigreg(everyone.reshape(-1, z.shape[-1]), generator=generator)
    total = sum(getattr(coeffs, name) * value for name, value in terms.items())
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    distributed.average_gradients(model.parameters())
    if recipe.grad_clip:
        torch.nn.utils.clip_grad_norm_(model.parameters(), recipe.grad_clip)
    optimizer.step()
    if replay is not None:
        replay.add(z, actions)
        replay(step)
    return total.detach(), {name: value.detach() for name, value in terms.items()}


def load_run(config: WorldTrainConfig, name: str,
             device: torch.device | str | None = None) -> WorldModel:
    """The saved run ``config`` (shipped in ``checkpoints/`` or cached as ``name``), in eval mode:
    notebooks 06 and 07 plan with trained models and train none."""
    model = WorldModel(config.model).to(get_device(device))
    path, shipped = checkpoint_paths(name)
    try:
        return load_or_train(path, model, None, identity(config), shipped)[0]
    except FileNotFoundError as error:
        raise FileNotFoundError(f"{error}. Notebook 05 trains chapter 05's run at its scale; "
                                "checkpoints/README.md names the command of every shipped file, "
                                "docs/running.md those of full scale.") from None


def load_world_model(path: str | Path, device: torch.device | str | None = None,
                     made_by: str = "python -m research.train_world --out PATH") -> WorldModel:
    """The world model at ``path``, in eval mode; a bad file's error names ``made_by``."""
    weights = load_made_by(path, made_by).get("model")
    if not isinstance(weights, dict) or "_extra_state" not in weights:
        raise ValueError(f"{path} holds no world model (expected a file written by {made_by})")
    return WorldModel.from_state_dict(weights).to(get_device(device)).eval()


ABLATION_SUFFIXES = {"variance": "no_variance", "covariance": "no_covariance",
                     "temporal": "no_temporal", "inverse_dynamics": "no_idm"}  # file names
ABLATABLE_TERMS = tuple(ABLATION_SUFFIXES)


def ablation_config(config: WorldTrainConfig, *without: str) -> WorldTrainConfig:
    """``config`` with the coefficients of the terms in ``without`` set to 0 (paper, Table 4)."""
    return replace(config, coeffs=replace(config.coeffs, **{term: 0.0 for term in without}))


def identity(config: WorldTrainConfig, step=None) -> dict:
    """What a checkpoint stores to recognise the run ``config`` (and the ranges of its walls)."""
    always = ("steps", "batch_size", "lr", "n_trajectories", "rollout_steps", "seed")
    edited = step_identity(step, world_model_step)
    if config.walls > 1:
        edited["wall_x_ranges"] = [list(r) for r in WALL_X_RANGES[config.walls]]
    return run_identity(config, always, **edited)
