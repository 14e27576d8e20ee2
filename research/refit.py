"""A new MLP predictor for a trained world model, fitted on its frozen latents.

The shipped pair that notebook 06's experiment 4 loads at every scale,
``checkpoints/world_model_class_long20k.pt`` and ``..._long20k_mlp.pt``, is
:func:`shipped_pair`; ``python -m research.train_world --refit TRAINED.pt --out FILE.pt``
writes a refit (:func:`refit_predictor`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.envs import generate_trajectories
from ebjepa_tutorial.losses.world import multistep_prediction_loss, with_still_steps
from ebjepa_tutorial.models.world import WorldModel
from ebjepa_tutorial.training.checkpoints import run_identity
from ebjepa_tutorial.training.loop import History, step_generator
from ebjepa_tutorial.training.world import TRAJECTORY_ACTIONS, WorldTrainConfig
from ebjepa_tutorial.utils import check_fields, get_device, is_int_at_least, is_positive

from .fitting import fit, trajectory_latents


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
            "rollout_steps": (lambda k: is_int_at_least(1)(k) and k <= TRAJECTORY_ACTIONS,
                              f"an int in 1..{TRAJECTORY_ACTIONS} (the actions per trajectory)"),
        })
        if not 0 < self.decay_fraction <= 1 or not 0 <= self.stay_probability < 1:
            raise ValueError("need 0 < decay_fraction <= 1 and 0 <= stay_probability < 1, got "
                             f"{self.decay_fraction} and {self.stay_probability}")


def shipped_pair() -> tuple[WorldTrainConfig, RefitConfig]:
    """The shipped refit's base run (chapter 06's long run, the paper's recipe, for 20,000
    steps: ``world_model_class_long20k``) and the refit of ``..._long20k_mlp`` (the defaults)."""
    return replace(preset("06", "class").longer.paper, steps=20_000), RefitConfig()


def refit_identity(config: RefitConfig, base: dict) -> dict:
    """What a refitted model's checkpoint stores: the refit and the base run's identity."""
    return run_identity(config, base=base)


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
    shape = replace(model.config, predictor="mlp", predictor_hidden=config.hidden)
    new = WorldModel(shape).to(device)
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
