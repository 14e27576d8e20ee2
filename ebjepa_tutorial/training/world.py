"""Training and checking the Two Rooms world model (notebook 05; its checkpoint serves 06).

Data: offline trajectories of the paper's data policy, generated once as
positions and actions (cheap) and rendered to frames batch by batch. Each
training batch is ``batch_size`` random trajectories of ``17`` frames, or
windows cut from them.

Two recipes train the same loss: the paper's (:class:`WorldTrainConfig`'s
defaults, :func:`paper_recipe`) and the course's (:func:`course_recipe`, the
class preset), which learns more per CPU-minute. Each step is
:func:`world_model_step`, the code notebook 05 shows and can hand in edited.

Shipped checkpoint: ``python -m research.train_world --out PATH``
trains the class-scale model and writes it. With ``--refit TRAINED.pt`` it
instead fits a new MLP predictor on that model's frozen latents
(:func:`refit_predictor`).

Several processes (``torchrun``, see :mod:`ebjepa_tutorial.distributed`):
``batch_size`` is the global batch, and global batch = per-rank batch x world
size. Every rank draws the same global batch (seeded by the step) and renders
only its own trajectories; the step averages the gradients over the ranks. The
model has no batch norm (its norm is a LayerNorm, per sample), so W ranks
compute the loss and gradients of one process on the whole batch. The refit
runs in one process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import torch

from .. import distributed
from ..envs import generate_trajectories, render
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
    with_still_steps,
)
from ..models.world import WORLD_CONFIGS, WorldConfig, WorldModel, trajectory_latents
from ..utils import check_fields, get_device, is_int_at_least, is_non_negative, is_positive
from .checkpoints import checkpoint_paths, load_checkpoint, run_identity, step_identity
from .loop import (
    History,
    fit,
    load_or_fit,
    load_or_train,
    resume,
    run_steps,
    saver,
    step_generator,
    training_state,
)

TRAJECTORY_ACTIONS = 16  # per training trajectory (17 frames, the paper's clips)
WALL_FRACTION_RULE = (lambda p: is_non_negative(p) and p <= 0.65,
                      "a number in [0, 0.65] (35% of trajectories start at the door)")
_ROLLOUT_RULE = (lambda k: is_int_at_least(1)(k) and k <= TRAJECTORY_ACTIONS,
                 f"an int in 1..{TRAJECTORY_ACTIONS} (the actions per trajectory)")
WEIGHT_DECAY = 1e-5  # AdamW's, as in the paper
# Latent replay (LatentReplay): each replayed update draws REPLAY_BATCH windows from the
# detached latents of the last REPLAY_CAPACITY training windows, with its own Adam
REPLAY_BATCH, REPLAY_CAPACITY, REPLAY_LR = 1024, 6400, 1e-3
LOG_EVERY, CHECKPOINT_EVERY = 10, 250  # steps between logged rows and resumable saves


@dataclass(frozen=True)
class Recipe:
    """How a run departs from the paper's training: the class recipe's ways to learn more per
    CPU-minute (notebook 05, section 4; RESULTS.md, chapter 05) and the long runs' guards
    (notebook 06, experiment 5). The defaults are the paper's: none of it."""

    # frames per training window, cut at a random offset from each drawn trajectory (0: the
    # whole trajectory). K + 1 frames are all the prediction loss reads, at about half the
    # encoder's cost of 17.
    window: int = 0
    # the share of trajectories that start in front of the middle wall, heading into it
    # (envs.trajectories.wall_starts)
    wall_fraction: float = 0.0
    # the share of imagined steps that are "still" (zero action, unchanged target)
    stay_probability: float = 0.0
    # predictor-only updates on replayed latents after each step (LatentReplay)
    replay_steps: int = 0
    # convolution weights and inputs in channels_last: about 1.45x faster on a CPU too, but
    # it changes the order of floating-point sums, so it is part of the run
    channels_last: bool = False
    # the last decay_steps steps lower the learning rate linearly towards 0 (0: constant, as
    # every shipped run but the course's long one)
    decay_steps: int = 0
    # every update (joint and replayed) scales its gradient down to at most this global norm
    # (0: none)
    grad_clip: float = 0.0

    def __post_init__(self):
        check_fields(self, {
            "window": (lambda w: w == 0 or is_int_at_least(2)(w) and w <= TRAJECTORY_ACTIONS + 1,
                       f"0 (whole trajectories) or an int in 2..{TRAJECTORY_ACTIONS + 1}"),
            "wall_fraction": WALL_FRACTION_RULE,
            "stay_probability": (lambda p: is_non_negative(p) and p < 1, "a number in [0, 1)"),
            "replay_steps": (is_int_at_least(0), "an int >= 0"),
            "decay_steps": (is_int_at_least(0), "an int >= 0 (0: a constant rate)"),
            "grad_clip": (is_non_negative, "a number >= 0 (0: no clipping)"),
        })


@dataclass(frozen=True)
class WorldTrainConfig:
    """One training run of the world model. Defaults: the paper's recipe with the class
    model (:func:`course_recipe` gives the class preset)."""

    model: WorldConfig = field(default_factory=lambda: WORLD_CONFIGS["class"])
    coeffs: WorldLossCoeffs = field(default_factory=WorldLossCoeffs)  # the paper's weights
    recipe: Recipe = field(default_factory=Recipe)  # the paper's; course_recipe: the class run's
    n_trajectories: int = 20_000  # offline data set (the paper: ~1.2 million windows)
    walls: int = 1  # 1: Two Rooms (the paper's world); 2: Three Rooms in a row (chapter 07)
    batch_size: int = 64  # trajectories of 17 frames per step (the paper: 384)
    steps: int = 1000  # the class preset trains 2,800 of the course's cheaper steps
    lr: float = 1e-3  # AdamW, as in the paper
    rollout_steps: int = 8  # K, the prediction horizon of the loss
    seed: int = 0

    def __post_init__(self):
        check_fields(self, {
            "n_trajectories": (is_int_at_least(1), "an int >= 1"),
            "walls": (lambda w: w in WALL_X_RANGES, f"one of {sorted(WALL_X_RANGES)} (Two or "
                                                    "Three Rooms)"),
            "batch_size": (is_int_at_least(2), "an int >= 2 (a batch of one has no variance)"),
            "steps": (is_int_at_least(1), "an int >= 1"),
            "lr": (is_positive, "a number > 0"),
            "rollout_steps": _ROLLOUT_RULE,
        })
        window = self.recipe.window
        if window and window < self.rollout_steps + 1:
            raise ValueError(f"window must hold rollout_steps + 1 = {self.rollout_steps + 1} "
                             f"frames, got {window}")
        if self.recipe.replay_steps and REPLAY_CAPACITY < self.batch_size:
            raise ValueError(f"the replay buffer holds {REPLAY_CAPACITY} windows, fewer than "
                             f"one batch of {self.batch_size}")
        if self.recipe.decay_steps > self.steps:
            raise ValueError(f"decay_steps must be in 0..steps={self.steps}, "
                             f"got {self.recipe.decay_steps}")


# How the course's class recipe trains differently from the paper's (notebook 05, section 4):
# half-length windows, a quarter of the trajectories heading into the middle wall, 15% still
# steps, 3 replayed predictor updates per step, channels_last, and an MLP predictor. The loss,
# its weights, K and the sizes stay the paper's.
COURSE_RECIPE = Recipe(window=9, wall_fraction=0.25, stay_probability=0.15, replay_steps=3,
                       channels_last=True)
COURSE_PREDICTOR = "mlp"


def course_recipe(config: WorldTrainConfig) -> WorldTrainConfig:
    """``config`` trained the course's way (the ``class`` and ``ci`` presets)."""
    return replace(config, recipe=COURSE_RECIPE,
                   model=replace(config.model, predictor=COURSE_PREDICTOR))


def paper_recipe(config: WorldTrainConfig) -> WorldTrainConfig:
    """``config`` trained the paper's way: whole 17-frame trajectories of the data policy, a
    GRU predictor, no still steps, no replay (chapter 06's longer runs, the ``full`` preset)."""
    return replace(config, recipe=Recipe(),
                   model=replace(config.model, predictor=WorldConfig.predictor))


def make_data(config: WorldTrainConfig) -> Trajectories:
    """The offline training trajectories of ``config`` (seeded by ``config.seed``)."""
    return generate_trajectories(config.n_trajectories, TRAJECTORY_ACTIONS, seed=config.seed,
                                 wall_fraction=config.recipe.wall_fraction, walls=config.walls)


def random_windows(data: Trajectories, index: torch.Tensor, window: int,
                   generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``window`` consecutive frames of each trajectory ``index``, from a random offset.

    index (B,) -> positions (B, window, 2) and the actions between them (B, window - 1, 2).
    """
    offsets = torch.randint(0, data.positions.shape[1] - window + 1, (len(index), 1),
                            generator=generator) + torch.arange(window)  # (B, window)
    rows = index[:, None]
    return data.positions[rows, offsets], data.actions[rows, offsets[:, :-1]]


class LatentReplay:
    """Extra predictor updates on the latents of recent batches: a replay buffer.

    Why: a joint step spends most of its time in the encoder and gives the
    predictor one update on ``batch_size`` windows. Updates of the predictor
    alone on stored latents cost little, so after each joint step this makes
    ``recipe.replay_steps`` more, each on ``REPLAY_BATCH`` windows drawn from the
    last ``REPLAY_CAPACITY`` windows' latents, detached (only the predictor and the
    action encoder learn here, with their own Adam), with the run's rollout loss
    and still steps. Older latents come from a slightly older encoder; a buffer
    of about a hundred steps keeps them close to today's.

    :meth:`add` stores a batch's latents ``(B, T, D)`` and actions ``(B, T-1, A)``;
    under torchrun every rank's are gathered, so all ranks hold the same buffer and
    draw the same global replay batch, each updating on its rows with the gradients
    averaged. Calling the object with ``step`` makes that step's updates.
    """

    STREAM = 2**40  # the replay's generators: seeded apart from the batches' (step_generator)

    def __init__(self, model: WorldModel, config: WorldTrainConfig, frames: int, device):
        distributed.per_rank_batch(REPLAY_BATCH)  # refuse an uneven split early
        self.model, self.config, self.batch = model, config, REPLAY_BATCH
        self.parameters = [*model.predictor.parameters(), *model.action_encoder.parameters()]
        self.optimizer = torch.optim.Adam(self.parameters, lr=REPLAY_LR)
        capacity, actions = REPLAY_CAPACITY, model.config.action_dim
        self.latents = torch.zeros(capacity, frames, model.latent_dim, device=device)
        self.actions = torch.zeros(capacity, frames - 1, actions, device=device)
        self.filled, self.head = 0, 0

    def add(self, z: torch.Tensor, actions: torch.Tensor) -> None:
        z, actions = distributed.gather_rows(z.detach()), distributed.gather_rows(actions)
        rows = (self.head + torch.arange(len(z), device=z.device)) % len(self.latents)
        self.latents[rows], self.actions[rows] = z, actions
        self.head = (self.head + len(z)) % len(self.latents)
        self.filled = min(self.filled + len(z), len(self.latents))

    def __call__(self, step: int) -> None:
        config = self.config
        generator = torch.Generator().manual_seed(self.STREAM + config.seed * 1_000_003 + step)
        for group in self.optimizer.param_groups:  # the joint step's schedule: a constant
            group["lr"] = REPLAY_LR * decay_factor(config, step)  # rate undid the decay
        for _ in range(config.recipe.replay_steps):
            pick = torch.randint(0, self.filled, (self.batch,), generator=generator)
            pick = distributed.local_rows(pick).to(self.latents.device)
            loss = multistep_prediction_loss(
                self.model.predict, self.latents[pick], self.actions[pick], config.rollout_steps,
                stay_probability=config.recipe.stay_probability, generator=generator,
                rand=distributed.rand_rows)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            distributed.average_gradients(self.parameters)
            if config.recipe.grad_clip:
                torch.nn.utils.clip_grad_norm_(self.parameters, config.recipe.grad_clip)
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
    """A fresh model whose input standardisation is fitted on 256 of the trajectories."""
    torch.manual_seed(config.seed)
    model = WorldModel(config.model)
    return model.fit_input_stats(data.frames(slice(0, 256)))


def new_optimizer(model: WorldModel, config: WorldTrainConfig) -> torch.optim.AdamW:
    """AdamW on every parameter at ``config.lr``, with the paper's weight decay."""
    return torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=WEIGHT_DECAY)


def decay_factor(config: WorldTrainConfig, step: int) -> float:
    """The share of the base rate that step ``step`` uses: 1, then a linear decay over the
    last ``decay_steps`` steps (``config.recipe``), ``min(1, (steps - step) / decay_steps)``,
    so the last step uses ``1 / decay_steps`` of it."""
    decay = config.recipe.decay_steps
    return min(1.0, (config.steps - step) / decay) if decay else 1.0


def learning_rate_decay(optimizer, config: WorldTrainConfig):
    """The schedule of ``config`` (:func:`decay_factor`); ``None`` when there is none."""
    if config.recipe.decay_steps == 0:
        return None
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: decay_factor(config, step))


# the names notebook 05's exercises give the two terms: there the learner's own functions
temporal_similarity, inverse_dynamics = temporal_similarity_loss, inverse_dynamics_loss


def world_model_step(model, optimizer, frames, actions, generator, config, step, replay=None):
    """One training step: the five terms, their weighted total, the update, the replay.

    Notebook 05 shows this code and hands it to :func:`train_world_model`. ``frames``
    ``(B, T, 2, 65, 65)``, ``actions`` ``(B, T-1, 2)``; ``generator`` draws the still steps
    and SIGReg's directions; ``step`` seeds the replay's draws. Returns ``(total, terms)``,
    detached: a 0-d tensor and a dict of 0-d tensors, for the history.
    """
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


def train_world_model(
    config: WorldTrainConfig,
    data: Trajectories | None = None,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    device: torch.device | str | None = None,
    step=world_model_step,
) -> tuple[WorldModel, History]:
    """Train a world model on ``data`` (default :func:`make_data`), each update a ``step``
    (notebook 05 passes its cell's); resume from ``checkpoint``. Batches come from
    generators seeded by ``(seed, step)``, so a resumed run sees the same ones. Under
    ``torchrun``, ``config.batch_size`` is the global batch (global batch = per-rank batch x
    world size); the step averages gradients over ranks and rank 0 alone writes ``checkpoint``.
    """
    per_rank = distributed.per_rank_batch(config.batch_size)  # refuse an uneven split early
    data = make_data(config) if data is None else data
    device, run = get_device(device), identity(config, step)
    layout = torch.channels_last if config.recipe.channels_last else torch.contiguous_format
    model = new_model(config, data).to(device, memory_format=layout)
    optimizer = new_optimizer(model, config)
    scheduler = learning_rate_decay(optimizer, config)
    frames = config.recipe.window or data.positions.shape[1]
    replay = LatentReplay(model, config, frames, device) if config.recipe.replay_steps else None
    start, history = resume(checkpoint, model, optimizer, scheduler, run, after_step=replay)
    batch = _batches(config, data, torch.empty(per_rank, frames, 2, 65, 65), device)

    def update(batch, n: int):
        total, terms = step(model, optimizer, *batch, config, n, replay)
        if scheduler is not None:
            scheduler.step()
        return total, terms

    def state(done: int) -> dict:  # what resume() reads back; rank 0 alone writes
        return training_state(done, run, history, model, optimizer, scheduler, replay)

    run_steps(update, batch, config.steps, start_step=start, history=history,
              log_every=LOG_EVERY, desc="world model", progress=progress,
              after=saver(checkpoint, state, config.steps, CHECKPOINT_EVERY))
    model.eval()
    return model, history


def _batches(config: WorldTrainConfig, data: Trajectories, buffer: torch.Tensor, device):
    """``batch(step) -> (frames, actions, generator)``: this rank's rows of the global batch
    of step ``step``, rendered into ``buffer (b, T, 2, 65, 65)``, and the step's generator."""
    window = config.recipe.window

    def batch(step: int):
        generator = step_generator(config.seed, step)  # then draws still steps and SIGReg's
        index = torch.randint(0, len(data), (config.batch_size,), generator=generator)
        if not window:
            index = distributed.local_rows(index)  # every rank drew the global batch: keep ours
            frames = data.frames(index, out=buffer)
            return frames.to(device), data.actions[index].to(device), generator
        # the global batch's windows (positions only: cheap), then this rank's rows rendered
        windows = (*random_windows(data, index, window, generator), data.layouts[index])
        positions, actions, layouts = (distributed.local_rows(x) for x in windows)
        return render(positions, layouts, out=buffer).to(device), actions.to(device), generator

    return batch


def train_or_load(config: WorldTrainConfig, name: str,
                  device: torch.device | str | None = None,
                  step=world_model_step) -> tuple[WorldModel, History]:
    """The model of ``config``: loaded if this run was saved, else trained with ``step``.

    Looks for ``checkpoints/<name>.pt`` (shipped with the course), then
    ``data/cache/checkpoints/<name>.pt``; otherwise makes the run's data, trains
    (resumable from ``<name>.partial`` in the cache) and saves. A ``step`` whose code
    differs from :func:`world_model_step` (an edited one) is a run of its own
    (:func:`identity`): it never loads, or replaces, the course's run. Returns
    ``(model in eval mode, history)``, the model on
    ``device`` (default: the best available, cuda, mps, cpu) whether loaded or trained.
    """
    device = get_device(device)
    # a loaded file brings its input statistics too; it is read straight onto the device
    model = WorldModel(config.model).to(device)
    cache_path, shipped = checkpoint_paths(name)
    partial = cache_path.with_suffix(".partial")

    def train() -> History:
        trained, history = train_world_model(config, make_data(config), checkpoint=partial,
                                             device=device, step=step)
        model.load_state_dict(trained.state_dict())
        return history

    history = load_or_train(cache_path, model, train, identity(config, step), shipped,
                            partial=partial)
    return model.eval(), history


def load_world_model(path: str | Path, config: WorldConfig | None = None,
                     device: torch.device | str | None = None) -> WorldModel:
    """The trained model saved at ``path`` by :func:`main` (or by any ``{"model": state_dict}``).

    With ``config``, the checkpoint must have been trained with exactly that
    architecture; a mismatch raises a ``ValueError`` naming each difference.
    Returns the model in eval mode on ``device`` (default: the best available,
    cuda, mps, cpu).
    """
    state = load_checkpoint(path)
    weights = state.get("model") if isinstance(state, dict) else None
    if not isinstance(weights, dict) or "_extra_state" not in weights:
        raise ValueError(f"{path} holds no world model (expected a file written by "
                         "python -m research.train_world --out PATH)")
    if config is None:
        model = WorldModel.from_state_dict(weights)
    else:
        model = WorldModel(config)
        model.load_state_dict(weights)
    return model.to(get_device(device)).eval()


# -- a sharper predictor on frozen latents ----------------------------------------------------
@dataclass(frozen=True)
class RefitConfig:
    """A new MLP predictor for a trained world model, fitted on its frozen latents.

    Why: the GRU step learns the middle wall well far from the door but softly
    within ~16 px of it, where a planner then pushes into the wall (README,
    chapter 06). The encoder already knows where the door is; a predictor with
    two hidden layers learns the sharp rule from the same latents.
    """

    hidden: int = 128  # width of the MLP's two hidden layers
    n_trajectories: int = 40_000  # fresh data-policy trajectories, encoded once
    steps: int = 16_000
    batch_size: int = 1024  # rollout windows per step (latents only: cheap)
    lr: float = 1e-3  # Adam
    decay_fraction: float = 0.3  # the rate falls linearly to 0 over this share of the steps
    rollout_steps: int = 8  # K, as in training
    # Each imagined step is a zero action whose target is the unchanged latent with this
    # probability: the data policy never stands still, but a planner at its goal must.
    stay_probability: float = 0.15
    seed: int = 4242  # of the trajectories, the new weights and the batches

    def __post_init__(self):
        check_fields(self, {
            **{name: (is_int_at_least(1), "an int >= 1")
               for name in ("hidden", "n_trajectories", "steps", "batch_size")},
            "lr": (is_positive, "a number > 0"),
            "rollout_steps": _ROLLOUT_RULE,
        })
        if not 0 < self.decay_fraction <= 1 or not 0 <= self.stay_probability < 1:
            raise ValueError("need 0 < decay_fraction <= 1 and 0 <= stay_probability < 1, got "
                             f"{self.decay_fraction} and {self.stay_probability}")


def windows_with_stays(latents: torch.Tensor, actions: torch.Tensor, index: torch.Tensor,
                       start: torch.Tensor, stay: torch.Tensor):
    """Rollout windows of recorded latents with still steps spliced in.

    ``latents (N, T+1, D)``, ``actions (N, T, A)``; window ``b`` begins at frame
    ``start[b]`` of trajectory ``index[b]`` and has ``K = stay.shape[1]`` steps.
    Where ``stay[b, k]`` the action is zero and the target repeats the previous
    frame; elsewhere the trajectory's next action and frame follow. Needs
    ``start + K <= T``. Returns ``z0 (B, D)``, ``actions (B, K, A)``, ``targets (B, K, D)``.
    """
    k = torch.arange(stay.shape[1] + 1, device=latents.device)
    window = latents[index[:, None], start[:, None] + k]  # (B, K + 1, D)
    sequence, taken = with_still_steps(window, actions[index[:, None], start[:, None] + k[:-1]],
                                       stay)
    return sequence[:, 0], taken, sequence[:, 1:]


def refitted_model(model: WorldModel, config: RefitConfig) -> WorldModel:
    """A fresh model shaped like ``model`` but with ``config``'s MLP predictor."""
    return WorldModel(replace(model.config, predictor="mlp", predictor_hidden=config.hidden))


def refit_predictor(model: WorldModel, config: RefitConfig = RefitConfig(),
                    progress: bool = True,
                    device: torch.device | str | None = None) -> tuple[WorldModel, History]:
    """``model`` with a new MLP predictor and action encoder fitted on its frozen latents.

    The encoder (so the planning energy) and the inverse-dynamics head are
    kept. The loss is the training loss's K-step rollout error
    (:func:`~ebjepa_tutorial.losses.world.multistep_prediction_loss`) on
    :func:`windows_with_stays`; the targets are fixed, so no regulariser is
    needed. ``model`` encodes on its own device (it is not moved); the latents,
    the new model and the fit are on ``device`` (default: the best available).
    Returns ``(new model in eval mode, on device, history)``.
    """
    device = get_device(device)
    data = generate_trajectories(config.n_trajectories, seed=config.seed)
    # (N, T+1, D) and (N, T, 2)
    latents, actions = trajectory_latents(model, data).to(device), data.actions.to(device)
    torch.manual_seed(config.seed)
    new = _with_new_predictor(model, config, device)
    optimizer, scheduler = _refit_optimizer(new, config)
    k = config.rollout_steps
    batch = _refit_batches(latents, actions, config, device)

    def loss(window):
        z0, actions, targets = window
        sequence = torch.cat([z0[:, None], targets], dim=1)
        return multistep_prediction_loss(new.predict, sequence, actions, k), {}

    history = fit(new, optimizer, loss, batch, config.steps, scheduler=scheduler, log_every=50,
                  desc="predictor refit", progress=progress)
    return new.eval(), history


def _with_new_predictor(model: WorldModel, config: RefitConfig, device) -> WorldModel:
    """A copy of ``model`` on ``device`` whose predictor and action encoder are new (the MLP
    of ``config``); the encoder, the inverse-dynamics head and the input statistics kept."""
    new = refitted_model(model, config).to(device)
    new.load_state_dict({name: value for name, value in model.state_dict().items()
                         if not name.startswith(("predictor.", "action_encoder.", "_extra"))},
                        strict=False)
    return new


def _refit_optimizer(new: WorldModel, config: RefitConfig):
    """Adam on the new predictor and action encoder (the loss reaches only these: the latents
    are precomputed), its rate falling linearly to 0 over the last ``decay_fraction``."""
    optimizer = torch.optim.Adam([*new.predictor.parameters(), *new.action_encoder.parameters()],
                                 lr=config.lr)
    decay = config.decay_fraction * config.steps
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: min(1.0, (config.steps - step) / decay))
    return optimizer, scheduler


def _refit_batches(latents: torch.Tensor, actions: torch.Tensor, config: RefitConfig, device):
    """``batch(step)``: :func:`windows_with_stays` of ``config.batch_size`` random windows of
    the latents ``(N, T+1, D)`` and actions ``(N, T, 2)``, drawn on the CPU (the same windows on
    every device), gathered on ``device``."""
    k, last_start = config.rollout_steps, actions.shape[1] - config.rollout_steps

    def batch(step: int):
        generator = step_generator(config.seed, step)
        index = torch.randint(0, len(latents), (config.batch_size,), generator=generator)
        start = torch.randint(0, last_start + 1, (config.batch_size,), generator=generator)
        stay = torch.rand(config.batch_size, k, generator=generator) < config.stay_probability
        return windows_with_stays(latents, actions, *(t.to(device) for t in (index, start, stay)))

    return batch


def refit_identity(config: RefitConfig, base: dict) -> dict:
    """What a refitted model's checkpoint stores: the refit and the base run's identity."""
    return run_identity(config, base=base)


def refit_or_load(model: WorldModel, base: WorldTrainConfig, config: RefitConfig,
                  name: str, device: torch.device | str | None = None) -> WorldModel:
    """``model`` (trained with ``base``) with its predictor refitted by ``config``: loaded
    from ``checkpoints/<name>.pt`` or the cache if one was saved for exactly these, else
    refitted and saved to the cache. Returns the new model in eval mode, on ``device``
    (default: the best available)."""
    device = get_device(device)
    return load_or_fit(name, refitted_model(model, config).to(device),
                       lambda: refit_predictor(model, config, device=device),
                       refit_identity(config, identity(base)))


ABLATABLE_TERMS = ("variance", "covariance", "temporal", "inverse_dynamics")
ABLATION_SUFFIXES = {"variance": "no_variance", "covariance": "no_covariance",
                     "temporal": "no_temporal", "inverse_dynamics": "no_idm"}  # file names


def ablation_config(config: WorldTrainConfig, *without: str) -> WorldTrainConfig:
    """``config`` with the coefficients of the terms in ``without`` set to 0 (paper, Table 4)."""
    unknown = set(without) - set(ABLATABLE_TERMS)
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}; choose from {ABLATABLE_TERMS}")
    return replace(config, coeffs=replace(config.coeffs, **{term: 0.0 for term in without}))


def with_coeffs(config: WorldTrainConfig, pairs: list[str]) -> WorldTrainConfig:
    """``config`` with loss weights set from ``"name=value"`` strings, e.g. ``["covariance=1"]``."""
    names = [f.name for f in fields(WorldLossCoeffs)]
    values = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or name not in names:
            raise ValueError(f"--coeff wants name=value with a name from {names}, got {pair!r}")
        try:
            values[name] = float(value)
        except ValueError:
            raise ValueError(f"--coeff {pair!r}: {value!r} is not a number") from None
        if not math.isfinite(values[name]) or values[name] < 0:
            raise ValueError(f"--coeff {pair!r}: a loss weight must be finite and >= 0")
    return replace(config, coeffs=replace(config.coeffs, **values))


def identity(config: WorldTrainConfig, step=None) -> dict:
    """What a checkpoint stores to recognise the run of ``config``. With several walls it
    records the ranges the walls are drawn from too, so that a model of one geometry never
    loads as the model of another; with an edited ``step``, a hash of its code
    (:func:`~.checkpoints.step_identity`)."""
    always = ("steps", "batch_size", "lr", "n_trajectories", "rollout_steps", "seed")
    edited = step_identity(step, world_model_step)
    if config.walls == 1:
        return run_identity(config, always, **edited)
    return run_identity(config, always, **edited,
                        wall_x_ranges=[list(r) for r in WALL_X_RANGES[config.walls]])
